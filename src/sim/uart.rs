//! What a UART set to one baud rate reads from bytes sent at another: the
//! simulator's model of a master and drives that disagree on the rate.
//!
//! A pty carries bytes whatever the rate set on it, so the simulator itself
//! turns the bytes into the line's levels at the sender's rate (8N1: a low
//! start bit, eight data bits LSB first, a high stop bit, high when idle)
//! and samples them as a receiver at the other rate does: it waits for a
//! falling edge, samples each bit in its middle, and reads a low stop bit as
//! a framing error, which Linux hands over as a NUL byte (termios without
//! `IGNPAR` or `PARMRK`). The result is the garbage a real wrong rate gives:
//! requests a drive cannot read (so it stays silent), replies a master
//! cannot frame.

/// The bytes a receiver at `read_baud` makes of `bytes` sent back to back
/// at `sent_baud`.
pub(crate) fn resample(bytes: &[u8], sent_baud: u32, read_baud: u32) -> Vec<u8> {
    if sent_baud == read_baud || sent_baud == 0 || read_baud == 0 {
        return bytes.to_vec();
    }
    let bit = 1.0 / f64::from(sent_baud);
    let level = |t: f64| -> bool {
        if t < 0.0 {
            return true;
        }
        // Truncation is the point: the bit this instant falls in.
        let i = (t / bit) as usize;
        match bytes.get(i / 10) {
            None => true,
            Some(byte) => match i % 10 {
                0 => false,
                9 => true,
                d => (byte >> (d - 1)) & 1 == 1,
            },
        }
    };
    let end = bytes.len() as f64 * 10.0 * bit;
    let sample = 1.0 / f64::from(read_baud);
    // A UART looks for the start edge at 16 times its rate; a finer step
    // at the faster of the two rates finds the same edges.
    let step = (bit.min(sample) / 16.0).max(end / 1_000_000.0);
    let mut out = Vec::new();
    let mut idle = true;
    let mut t = 0.0;
    while t < end {
        let now = level(t);
        if idle && !now && !level(t + sample / 2.0) {
            let mut byte = 0u8;
            for d in 0..8 {
                if level(t + sample * (1.5 + f64::from(d))) {
                    byte |= 1 << d;
                }
            }
            let stop = level(t + sample * 9.5);
            out.push(if stop { byte } else { 0 });
            t += sample * 9.5;
            // After a framing error the receiver waits for the line to go
            // high before it looks for the next start bit.
            idle = stop;
            continue;
        }
        idle = now;
        t += step;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive::DriveRequest;
    use crate::modbus::rtu_frame;

    #[test]
    fn the_same_rate_reads_what_was_sent() {
        let frame = DriveRequest::ReadStatus.frame(1).unwrap();
        assert_eq!(resample(&frame, 9_600, 9_600), frame);
    }

    #[test]
    fn a_receiver_twice_as_fast_reads_the_start_bit_as_a_data_bit() {
        // 0xFF at 9600: a start bit two 19200-bits long, then highs: the
        // second half of the start bit is read as data bit 0.
        assert_eq!(resample(&[0xFF], 9_600, 19_200), [0xFE]);
        // 0x00 at 9600: nine low bits, eighteen at 19200: the stop bit is
        // low, a framing error, delivered as NUL; then the line must go
        // high before anything else is read.
        assert_eq!(resample(&[0x00], 9_600, 19_200), [0x00]);
    }

    #[test]
    fn a_receiver_slower_than_the_sender_reads_fewer_bytes() {
        let frame = DriveRequest::ReadStatus.frame(1).unwrap();
        let read = resample(&frame, 115_200, 9_600);
        assert!(read.len() < frame.len(), "{read:02x?}");
    }

    #[test]
    fn a_request_at_another_rate_is_no_frame_at_any_common_rate() {
        let frame = DriveRequest::ReadStatus.frame(1).unwrap();
        for sent in [9_600, 19_200, 38_400, 57_600, 115_200] {
            for read in [9_600, 19_200, 38_400, 57_600, 115_200] {
                let bytes = resample(&frame, sent, read);
                assert_eq!(
                    rtu_frame::decode(&bytes).is_ok(),
                    sent == read,
                    "{sent} -> {read}: {bytes:02x?}"
                );
            }
        }
    }
}
