//! Precise sleeps for wire timing.
//!
//! tokio's timer wheel has a 1 ms resolution, so `tokio::time::sleep(1.75 ms)`
//! sleeps 2 to 3 ms: on a 115200 baud bus that alone would cost a fifth of the
//! throughput. The RTU silences (t3.5 = 1.75 ms) and the simulator's character
//! pacing (86.8 us) use a `timerfd` instead, which the kernel fires to within
//! microseconds and tokio watches like any other file descriptor.

use std::io;
use std::os::fd::{AsFd, AsRawFd, RawFd};
use std::time::Instant;

use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use tokio::io::unix::AsyncFd;

struct Fd(TimerFd);

impl AsRawFd for Fd {
    fn as_raw_fd(&self) -> RawFd {
        self.0.as_fd().as_raw_fd()
    }
}

/// How much of each sleep is spun rather than slept (see [`PreciseTimer::sleep_until`]).
pub const SPIN: std::time::Duration = std::time::Duration::from_micros(60);

/// A reusable high-resolution timer for one task.
pub struct PreciseTimer {
    fd: AsyncFd<Fd>,
}

impl PreciseTimer {
    /// Creates the timer; must be called inside a tokio runtime.
    pub fn new() -> io::Result<Self> {
        let timer = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )?;
        // SAFETY: `Fd` owns the timerfd and never closes or replaces it
        // while the `AsyncFd` holds it; it is dropped with the `AsyncFd`.
        #[allow(unsafe_code)]
        let fd = unsafe { AsyncFd::register(Fd(timer)) }.map_err(io::Error::from)?;
        Ok(Self { fd })
    }

    /// Sleeps until `deadline` (returns at once if it has passed).
    ///
    /// The kernel wakes a thread tens of microseconds after its timer fires;
    /// so the timer is set [`SPIN`] early and the last stretch is spun, which
    /// keeps the wire's silences within a few microseconds of their length.
    pub async fn sleep_until(&mut self, deadline: Instant) -> io::Result<()> {
        self.sleep(deadline, SPIN).await
    }

    /// Sleeps until `deadline`, spinning (not sleeping) when it is at most
    /// `spin` away: for a thread that must not risk a wake-up just before a
    /// deadline it is about to act on.
    pub async fn sleep_until_spinning(
        &mut self,
        deadline: Instant,
        spin: std::time::Duration,
    ) -> io::Result<()> {
        self.sleep(deadline, spin.max(SPIN)).await
    }

    /// Sleeps until about `deadline` without spinning: for waits where tens
    /// of microseconds late do not matter, to save the CPU.
    pub async fn sleep_until_relaxed(&mut self, deadline: Instant) -> io::Result<()> {
        self.sleep(deadline, std::time::Duration::ZERO).await
    }

    async fn sleep(&mut self, deadline: Instant, spin: std::time::Duration) -> io::Result<()> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left <= spin {
                while Instant::now() < deadline {
                    std::hint::spin_loop();
                }
                return Ok(());
            }
            let left = left - spin;
            // A zero expiration would disarm the timer; `left` is never zero here.
            self.fd.get_ref().0.set(
                Expiration::OneShot(TimeSpec::from_duration(left)),
                TimerSetTimeFlags::empty(),
            )?;
            let mut guard = self.fd.readable().await?;
            // Consume the expiration count; a stale readiness gives WouldBlock,
            // which clears it, and the loop re-checks the clock either way.
            let _ = guard.try_io(|fd| fd.get_ref().0.wait().map_err(io::Error::from));
        }
    }
}

/// Asks the kernel to fire this thread's timers without the default 50 us of
/// slack. Best effort: without it timing is only a little coarser.
pub fn tighten_timer_slack() {
    if let Err(e) = nix::sys::prctl::set_timerslack(1) {
        tracing::debug!("could not tighten the timer slack: {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn sleeps_to_the_deadline_not_before() {
        tighten_timer_slack();
        let mut timer = PreciseTimer::new().unwrap();
        for _ in 0..20 {
            let start = Instant::now();
            let deadline = start + Duration::from_micros(1750);
            timer.sleep_until(deadline).await.unwrap();
            // Never early; how late it is depends on the machine's load, so
            // that is measured by the benchmark, not asserted here.
            assert!(Instant::now() >= deadline);
        }
        // A deadline in the past returns at once.
        timer.sleep_until(Instant::now()).await.unwrap();
    }
}
