//! Precise sleeps for wire timing, without spinning.
//!
//! tokio's timer wheel has a 1 ms resolution, so `tokio::time::sleep(1.75 ms)`
//! sleeps 2 to 3 ms: on a 115200 baud bus that alone would cost a fifth of the
//! throughput. The RTU silences (t3.5 = 1.75 ms) and the simulator's reply
//! pacing use a `timerfd` instead, which the kernel fires to within
//! microseconds and tokio watches like any other file descriptor.
//!
//! The thread then runs some tens of microseconds after the timer fired
//! (longer in a virtual machine, far longer on a machine busy with other
//! work). A sleep that must not end late arms its timer that much early: the
//! timer learns how late its wake-ups come ([`WakeLatency`], a low quantile,
//! so most wake-ups still come at or after the deadline), and the few that
//! come early wait out the rest of a stretch no longer than that, instead of
//! spinning through a fixed stretch before every deadline.

use std::io;
use std::os::fd::{AsFd, AsRawFd, RawFd};
use std::time::{Duration, Instant};

use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use tokio::io::unix::AsyncFd;

struct Fd(TimerFd);

impl AsRawFd for Fd {
    fn as_raw_fd(&self) -> RawFd {
        self.0.as_fd().as_raw_fd()
    }
}

/// How late the kernel runs a thread after its timer fired, learned from
/// the timer's own wake-ups: a running estimate of their lower quartile
/// (each wake-up later than the estimate raises it by [`WakeLatency::UP`],
/// each one earlier lowers it by three times that, so a quarter of the
/// wake-ups come before it). Pure: time is passed in.
///
/// A quantile, not a mean: the rare wake-up milliseconds late (a busy
/// machine) moves it by a microsecond, not by its own size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WakeLatency {
    estimate: Duration,
}

impl WakeLatency {
    /// The step up after a wake-up later than the estimate.
    pub const UP: Duration = Duration::from_micros(1);
    /// The step down after one earlier: three times [`UP`](Self::UP), for
    /// the lower quartile.
    pub const DOWN: Duration = Duration::from_micros(3);
    /// The most a timer is armed early: a wake-up that comes that early is
    /// waited out, so this bounds the wait.
    pub const MAX: Duration = Duration::from_micros(150);

    /// Nothing learned yet: timers are armed at their deadline.
    pub const fn new() -> Self {
        Self {
            estimate: Duration::ZERO,
        }
    }

    /// How much before a deadline to arm the timer.
    pub fn lead(&self) -> Duration {
        self.estimate
    }

    /// A timer armed to fire at `fired` woke its thread at `woke`.
    pub fn observe(&mut self, fired: Instant, woke: Instant) {
        let late = woke.saturating_duration_since(fired);
        self.estimate = if late > self.estimate {
            (self.estimate + Self::UP).min(Self::MAX)
        } else {
            self.estimate.saturating_sub(Self::DOWN)
        };
    }
}

impl Default for WakeLatency {
    fn default() -> Self {
        Self::new()
    }
}

/// How a sleep ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Wake {
    /// At the deadline, never before: armed early by the learned latency,
    /// and a wake-up that comes early waits out the rest.
    Precise,
    /// About at the deadline, up to the learned latency before it: for a
    /// thread that prepares what it does at the deadline.
    Near,
    /// At the deadline or later, by the wake-up latency: for waits where
    /// that does not matter.
    Relaxed,
}

/// A reusable high-resolution timer for one task.
pub struct PreciseTimer {
    fd: AsyncFd<Fd>,
    latency: WakeLatency,
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
        Ok(Self {
            fd,
            latency: WakeLatency::new(),
        })
    }

    /// Sleeps until `deadline`, never returning before it (returns at once
    /// if it has passed). The timer is armed the learned wake-up latency
    /// early; a wake-up that still comes early waits out the rest.
    pub async fn sleep_until(&mut self, deadline: Instant) -> io::Result<()> {
        self.sleep(deadline, Wake::Precise).await
    }

    /// Sleeps until about `deadline`: never more than the learned wake-up
    /// latency before it, and never waiting out a stretch. For a thread
    /// that gets something ready just before a deadline it then keeps
    /// precisely.
    pub async fn sleep_until_near(&mut self, deadline: Instant) -> io::Result<()> {
        self.sleep(deadline, Wake::Near).await
    }

    /// Sleeps until `deadline` or a little after (the wake-up latency): for
    /// waits where tens of microseconds late do not matter.
    pub async fn sleep_until_relaxed(&mut self, deadline: Instant) -> io::Result<()> {
        self.sleep(deadline, Wake::Relaxed).await
    }

    /// The wake-up latency learned so far.
    pub fn latency(&self) -> WakeLatency {
        self.latency
    }

    async fn sleep(&mut self, deadline: Instant, wake: Wake) -> io::Result<()> {
        loop {
            let now = Instant::now();
            if now >= deadline {
                return Ok(());
            }
            let lead = match wake {
                Wake::Precise | Wake::Near => self.latency.lead(),
                Wake::Relaxed => Duration::ZERO,
            };
            if deadline - now <= lead {
                // Closer to the deadline than a wake-up would come.
                self.rest(deadline, wake);
                return Ok(());
            }
            let fire = deadline - lead;
            // A zero expiration would disarm the timer; `fire - now` is
            // never zero here.
            self.fd.get_ref().0.set(
                Expiration::OneShot(TimeSpec::from_duration(fire - now)),
                TimerSetTimeFlags::empty(),
            )?;
            let mut guard = self.fd.readable().await?;
            // Consume the expiration count; a stale readiness gives
            // WouldBlock, which clears it, and the loop re-checks the clock.
            // Only a wake-up by this timer teaches its latency.
            let fired = guard.try_io(|fd| fd.get_ref().0.wait().map_err(io::Error::from));
            if matches!(fired, Ok(Ok(()))) {
                let woke = Instant::now();
                self.latency.observe(fire, woke);
                if woke < deadline {
                    self.rest(deadline, wake);
                    return Ok(());
                }
                return Ok(());
            }
        }
    }

    /// The rest of a sleep woken (or begun) within the wake-up latency of
    /// `deadline`: waited out if it must not end early.
    fn rest(&self, deadline: Instant, wake: Wake) {
        if wake == Wake::Precise {
            while Instant::now() < deadline {
                std::hint::spin_loop();
            }
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

    const US: Duration = Duration::from_micros(1);

    #[tokio::test]
    async fn sleeps_to_the_deadline_not_before() {
        tighten_timer_slack();
        let mut timer = PreciseTimer::new().unwrap();
        for _ in 0..50 {
            let start = Instant::now();
            let deadline = start + Duration::from_micros(1750);
            timer.sleep_until(deadline).await.unwrap();
            // Never early; how late it is depends on the machine's load, so
            // that is measured by the benchmark, not asserted here.
            assert!(Instant::now() >= deadline);
        }
        // A deadline in the past returns at once.
        timer.sleep_until(Instant::now()).await.unwrap();
        // Near returns at most the learned latency early.
        let deadline = Instant::now() + Duration::from_micros(1750);
        timer.sleep_until_near(deadline).await.unwrap();
        assert!(Instant::now() + timer.latency().lead() >= deadline);
    }

    #[test]
    fn the_latency_settles_on_the_lower_quartile_of_the_wake_ups() {
        let mut latency = WakeLatency::new();
        let t0 = Instant::now();
        // Wake-ups 40, 50, 60 and 70 us late, in turn: the lower quartile
        // is between 40 and 50.
        for i in 0..4000u32 {
            let late = 40 + 10 * (i % 4);
            latency.observe(t0, t0 + US * late);
        }
        let lead = latency.lead();
        assert!((38 * US..=52 * US).contains(&lead), "{lead:?}");
    }

    #[test]
    fn a_rare_late_wake_up_barely_moves_it_and_it_stays_bounded() {
        let mut latency = WakeLatency::new();
        let t0 = Instant::now();
        for _ in 0..500 {
            latency.observe(t0, t0 + US * 20);
        }
        let before = latency.lead();
        // One wake-up 10 ms late: one step.
        latency.observe(t0, t0 + Duration::from_millis(10));
        assert!(latency.lead() <= before + WakeLatency::UP);
        // Always late: never more than the bound.
        for _ in 0..10_000 {
            latency.observe(t0, t0 + Duration::from_millis(10));
        }
        assert_eq!(latency.lead(), WakeLatency::MAX);
        // A wake-up before its timer fired (a clock read early) lowers it.
        let high = latency.lead();
        latency.observe(t0 + US, t0);
        assert!(latency.lead() < high);
    }
}
