//! When each request of a connection arrived, pure: a client's requests
//! wait in the connection's read buffer while its pipeline is full (behind
//! a slow bus), and the time they waited there counts against the bus's
//! `queue_timeout_ms` like their wait in the bus queue
//! ([`crate::control::live::queue_wait`]): a request the client has given
//! up on (and may have sent again) is not sent late.
//!
//! The buffer is read in chunks and framed later, so what is known is when
//! each read ended; a frame arrived when the read holding its last byte
//! did.

use std::collections::VecDeque;
use std::time::Instant;

/// The reads whose bytes are still in the buffer.
#[derive(Debug, Default)]
pub struct Arrivals {
    /// Each read: where its bytes end (counted since the connection
    /// opened) and when it ended.
    reads: VecDeque<(u64, Instant)>,
    /// Bytes read since the connection opened.
    read: u64,
    /// Bytes taken out of the buffer since the connection opened.
    taken: u64,
}

impl Arrivals {
    /// `n` bytes were read into the buffer at `at`.
    pub fn read(&mut self, n: usize, at: Instant) {
        if n == 0 {
            return;
        }
        self.read += n as u64;
        self.reads.push_back((self.read, at));
    }

    /// A frame of `n` bytes was taken from the front of the buffer: when
    /// its last byte arrived (`None`: its bytes were never read, which the
    /// buffer cannot do).
    pub fn take(&mut self, n: usize) -> Option<Instant> {
        self.taken += n as u64;
        let at = self
            .reads
            .iter()
            .find(|(end, _)| *end >= self.taken)
            .map(|(_, at)| *at);
        while self
            .reads
            .front()
            .is_some_and(|(end, _)| *end <= self.taken)
        {
            self.reads.pop_front();
        }
        at
    }

    /// The buffer was emptied: nothing in it is a request any more.
    pub fn clear(&mut self) {
        self.taken = self.read;
        self.reads.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_frame_arrived_with_the_read_that_held_its_last_byte() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let mut a = Arrivals::default();
        // Two whole 12-byte frames in one read, then one split over two.
        a.read(24, ms(0));
        a.read(5, ms(10));
        a.read(7, ms(20));
        assert_eq!(a.take(12), Some(ms(0)));
        assert_eq!(a.take(12), Some(ms(0)));
        assert_eq!(a.take(12), Some(ms(20)));
        // Everything taken: nothing kept.
        assert!(a.reads.is_empty());
        // A frame of a read not taken whole: the rest stays for the next.
        a.read(30, ms(30));
        assert_eq!(a.take(12), Some(ms(30)));
        assert_eq!(a.reads.len(), 1);
        a.clear();
        a.read(12, ms(40));
        assert_eq!(a.take(12), Some(ms(40)));
        // Never more than the buffer holds.
        assert_eq!(a.take(1), None);
    }
}
