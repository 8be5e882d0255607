//! The silence before requests (`[bus] interframe`), end to end on the
//! simulator through a real pty, with drives that part frames after 0.35 ms
//! and strict ones that need the spec's t3.5 (a request that comes sooner
//! is one garbled frame to them, unanswered):
//! - "auto" learns the fast drives' gaps and keeps a strict drive on the
//!   spec; clients' requests never wait on a trial;
//! - a drive replaced by a strict one is noticed at its first miss and
//!   served at the spec from then on, with no client error;
//! - a simulator kept from running (a late host) costs a drive its gap
//!   until one poll checks it again, not a relearning;
//! - commands and emergencies never go after an unconfirmed gap;
//! - "spec" leaves no silence shorter than t3.5.
//!
//! Every wait is for an event (a figure in the bus's counters), bounded
//! only against a hang. The reply timeout is fixed and long (250 ms): a
//! simulator the machine keeps from running is then late, not silent, and
//! puts no drive back on the spec; a drive that does not understand a
//! request never answers it. The silences checked are the master's own
//! (the bus monitor's `silence_us`): the wire's are longer, never shorter.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use crate::support::{TestDaemon, bounded, eventually};
use drivegate::bus::handle::JobOptions;
use drivegate::bus::{BusHandle, Origin, Priority};
use drivegate::drive::{DriveReply, DriveRequest};
use drivegate::monitor::record::{Direction, FrameRecord};
use drivegate::plant::Bus;
use tokio_util::sync::CancellationToken;

const LIMIT: Duration = Duration::from_secs(90);
/// A whole test's bound, for one that hangs: each of its waits has
/// `LIMIT`, and a machine loaded many times over learns slowly.
const WHOLE: Duration = Duration::from_secs(240);
const SPEC_US: u32 = 1750;
/// 3.5 characters at 115200 baud and the adapter's 50 µs: the least gap
/// any request but a trial gets.
const FLOOR_US: u32 = 353;

fn config(interframe: &str, strict: &str, poll_interval_ms: u64) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
         [safety]\non_shutdown = \"none\"\n[monitor]\nring_frames = 20000\n\
         [[bus]]\nname = \"line\"\nport = \"sim\"\nresponse_timeout_ms = 250\nguard_ms = 50\n\
         poll_interval_ms = {poll_interval_ms}\ninterframe = {interframe}\nretries = 2\n\
         [bus.sim]\nturnaround_ms = 0.5\nframe_gap_us = 350\nstrict_units = [{strict}]\n"
    );
    for unit in 1..=4 {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\n"
        ));
    }
    toml
}

/// The gap `unit`'s requests get now, µs.
fn gap_us(bus: &BusHandle, unit: u8) -> Option<u32> {
    bus.stats()
        .drives
        .get(&unit)
        .map(|t| t.interframe.as_micros() as u32)
}

/// Waits until `enough` of `units` have had a learned gap (at most 1 ms)
/// at some moment (on a machine busy enough to keep the bus thread from
/// keeping short silences, a drive may take its backoff to learn); the
/// least gap of each seen.
async fn learned_each(bus: &BusHandle, units: &[u8], enough: usize) -> Vec<u32> {
    let mut seen = vec![SPEC_US; units.len()];
    eventually(LIMIT, "gaps learned", || {
        for (i, &u) in units.iter().enumerate() {
            seen[i] = seen[i].min(gap_us(bus, u).unwrap_or(SPEC_US));
        }
        (seen.iter().filter(|&&g| g <= 1000).count() >= enough).then(|| seen.clone())
    })
    .await
}

/// Clients reading the status of `units` back to back (commands), with an
/// emergency read of unit 1 now and then, until `stop`: their answered
/// reads as they go and, at the end, every error.
fn clients(
    bus: &BusHandle,
    units: &[u8],
    stop: &CancellationToken,
) -> (Arc<AtomicU64>, Vec<tokio::task::JoinHandle<Vec<String>>>) {
    let answered = Arc::new(AtomicU64::new(0));
    let tasks = units
        .iter()
        .map(|&unit| {
            let (bus, stop, answered) = (bus.clone(), stop.clone(), answered.clone());
            tokio::spawn(async move {
                let mut errors = Vec::new();
                let mut n = 0u32;
                while !stop.is_cancelled() {
                    n += 1;
                    let options = if unit == 1 && n.is_multiple_of(10) {
                        JobOptions::with_priority(Priority::Emergency)
                    } else {
                        JobOptions::default()
                    };
                    match bus.execute(unit, &DriveRequest::ReadStatus, options).await {
                        Ok(DriveReply::Status(_)) => {
                            answered.fetch_add(1, Ordering::Relaxed);
                        }
                        other => errors.push(format!("unit {unit}: {other:?}")),
                    }
                }
                errors
            })
        })
        .collect();
    (answered, tasks)
}

async fn errors_of(tasks: Vec<tokio::task::JoinHandle<Vec<String>>>) -> Vec<String> {
    let mut errors = Vec::new();
    for t in tasks {
        errors.extend(t.await.unwrap());
    }
    errors
}

/// A request the bus monitor holds.
#[derive(Debug, Clone, Copy)]
struct Request {
    seq: u64,
    unit: u8,
    /// From the poller (a poll, or a trial in idle time).
    poll: bool,
    /// The silence before it, µs, as the master measured it.
    silence: u32,
    /// Its reply was valid.
    answered: bool,
}

/// The requests the bus monitor holds, in order.
fn requests(bus: &Bus) -> Vec<Request> {
    let frames: Vec<FrameRecord> = bus.monitor().last(20_000);
    let mut out: Vec<Request> = Vec::new();
    for r in &frames {
        match r.direction {
            Direction::Request if r.unit != 0 => out.push(Request {
                seq: r.seq,
                unit: r.unit,
                poll: matches!(r.origin, Origin::Poller),
                silence: r.silence_us.unwrap_or(0),
                answered: false,
            }),
            Direction::Reply => {
                if let Some(last) = out.last_mut().filter(|q| q.unit == r.unit) {
                    last.answered = !r.outcome.is_fault();
                }
            }
            _ => {}
        }
    }
    out
}

/// Checks that no client's request went after a gap its drive had not
/// confirmed: every one at least the floor, and one shorter than the spec
/// at least twice the shortest silence after which the drive had answered
/// before it (a trial's; 100 µs for what the trial's measure may exceed
/// the level tried).
fn assert_clients_kept_confirmed_gaps(seen: &[Request]) {
    let mut shortest_answered = [u32::MAX; 256];
    for q in seen {
        if !q.poll && q.silence < SPEC_US {
            let confirmed_by = shortest_answered[usize::from(q.unit)];
            assert!(q.silence >= FLOOR_US, "{q:?}");
            assert!(
                confirmed_by != u32::MAX && q.silence + 100 >= 2 * confirmed_by,
                "{q:?}: the drive had answered after {confirmed_by} us at least"
            );
        }
        if q.answered {
            let s = &mut shortest_answered[usize::from(q.unit)];
            *s = (*s).min(q.silence);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_learns_fast_drives_and_keeps_a_strict_one_on_the_spec() {
    bounded(WHOLE, async {
        let d = TestDaemon::start(&config("\"auto\"", "4", 50)).await;
        let bus = d.plant.buses()[0].clone();
        let handle = bus.handle.clone();
        let stop = CancellationToken::new();
        let (answered, tasks) = clients(&handle, &[1, 2, 3, 4], &stop);
        // One fast drive learned will do: on a loaded machine the bus
        // thread keeps a short silence seldom, and each drive's trials wait
        // their backoff.
        let gaps = learned_each(&handle, &[1, 2, 3], 1).await;
        // Twice the shortest silence the drive answered, at least the floor,
        // far below the spec: the fast drives part frames after 0.35 ms.
        for &g in &gaps {
            assert!(g >= FLOOR_US, "{gaps:?}");
        }
        // The strict drive was tried (a poll after a shorter silence) and
        // stays on the spec.
        eventually(LIMIT, "a trial of the strict drive", || {
            requests(&bus)
                .iter()
                .any(|q| q.unit == 4 && q.poll && q.silence < SPEC_US - 100)
                .then_some(())
        })
        .await;
        // Far above the fast drives': a trial below half the spec never
        // passed (a simulator the machine keeps from running hears a longer
        // silence than the master left, so one level above may).
        let strict = gap_us(&handle, 4).unwrap_or(0);
        assert!(strict > 1400, "{strict} us");
        let before = answered.load(Ordering::Relaxed);
        eventually(LIMIT, "more reads", || {
            (answered.load(Ordering::Relaxed) > before + 100).then_some(())
        })
        .await;
        stop.cancel();
        let errors = errors_of(tasks).await;
        assert!(errors.is_empty(), "{errors:?}");
        // Clients' requests (commands and emergencies) went after confirmed
        // gaps only; the trials (shorter) were polls.
        let seen = requests(&bus);
        assert_clients_kept_confirmed_gaps(&seen);
        // Trials below the floor (how far down the ladder goes depends on
        // how often the machine let the master keep a silence that short)
        // were polls, every one.
        let below: Vec<_> = seen.iter().filter(|q| q.silence < FLOOR_US).collect();
        assert!(below.iter().all(|q| q.poll), "{below:?}");
        let sim = d.sim().stats();
        assert!(sim.merged_frames >= 1, "{sim}");
        d.stop().await;
    })
    .await;
}

/// The first of `units` to learn a gap (at most 1 ms) and keep it while
/// the bus polls it a while (its steps are over: an idle bus tries them
/// back to back); that gap, µs. On a machine busy enough to keep the bus
/// thread from keeping short silences, some drives take long to learn:
/// any one will do.
async fn settled_one(bus: &BusHandle, units: &[u8]) -> (u8, u32) {
    let mut last = vec![SPEC_US; units.len()];
    let mut same = vec![0u32; units.len()];
    eventually(LIMIT, "a settled gap", || {
        for (i, &u) in units.iter().enumerate() {
            let gap = gap_us(bus, u).unwrap_or(SPEC_US);
            same[i] = if gap == last[i] { same[i] + 1 } else { 0 };
            last[i] = gap;
        }
        (0..units.len())
            .find(|&i| same[i] >= 200 && last[i] <= 1000)
            .map(|i| (units[i], last[i]))
    })
    .await
}

/// Times `unit` fell back to the spec.
fn fallbacks(bus: &BusHandle, unit: u8) -> u64 {
    bus.stats()
        .drives
        .get(&unit)
        .map_or(0, |t| t.interframe_fallbacks)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drive_replaced_by_a_strict_one_is_served_at_the_spec_from_its_first_miss() {
    bounded(WHOLE, async {
        let d = TestDaemon::start(&config("\"auto\"", "", 200)).await;
        let bus = d.plant.buses()[0].clone();
        let handle = bus.handle.clone();
        let (unit, learned_gap) = settled_one(&handle, &[1, 2, 3, 4]).await;
        let stop = CancellationToken::new();
        let (answered, tasks) = clients(&handle, &[1, 2, 3, 4], &stop);
        // The drive is replaced by one that needs the spec's t3.5.
        let replaced_at = bus.monitor().frames();
        let fell_back = fallbacks(&handle, unit);
        d.sim()
            .set_frame_gap(unit, Some(Duration::from_micros(1750)))
            .unwrap();
        eventually(LIMIT, "the drive back on the spec", || {
            (fallbacks(&handle, unit) > fell_back).then_some(())
        })
        .await;
        let before = answered.load(Ordering::Relaxed);
        eventually(LIMIT, "more reads", || {
            (answered.load(Ordering::Relaxed) > before + 200).then_some(())
        })
        .await;
        stop.cancel();
        let errors = errors_of(tasks).await;
        assert!(
            errors.is_empty(),
            "no client error: {errors:?} (unit {unit} had {learned_gap} us)"
        );
        assert_eq!(gap_us(&handle, unit), Some(SPEC_US));
        // Its first miss after the replacement, and from then on every
        // request of a client to it after the spec's silence.
        let to_unit: Vec<Request> = requests(&bus)
            .into_iter()
            .filter(|q| q.unit == unit && q.seq >= replaced_at)
            .collect();
        let first_miss = to_unit
            .iter()
            .position(|q| !q.answered)
            .expect("the replaced drive missed a request");
        let after: Vec<&Request> = to_unit[first_miss + 1..]
            .iter()
            .filter(|q| !q.poll)
            .collect();
        assert!(after.len() > 20, "{to_unit:?}");
        assert!(after.iter().all(|q| q.silence >= SPEC_US), "{after:?}");
        // The retry of the missed request went after the spec's silence too.
        assert!(to_unit[first_miss + 1].silence >= SPEC_US, "{to_unit:?}");
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_simulator_kept_from_running_costs_a_drive_its_gap_until_one_poll_only() {
    bounded(WHOLE, async {
        let d = TestDaemon::start(&config("\"auto\"", "", 200)).await;
        let bus = d.plant.buses()[0].clone();
        let handle = bus.handle.clone();
        let (unit, held) = settled_one(&handle, &[1, 2, 3, 4]).await;
        // A client reads that drive back to back: it keeps its gap for far
        // more than the 20 reads after which a lone miss is checked again.
        let stop = CancellationToken::new();
        let (answered, tasks) = clients(&handle, &[unit], &stop);
        eventually(LIMIT, "reads at the learned gap", || {
            (answered.load(Ordering::Relaxed) > 200).then_some(())
        })
        .await;
        let before = fallbacks(&handle, unit);
        let stalled_at = bus.monitor().frames();
        // The machine keeps the simulator from running for longer than the
        // reply timeout: the request on the wire then gets no reply in time.
        // (If that request was another drive's poll, once more.)
        let sim = d.sim();
        eventually(LIMIT, "the drive back on the spec", || {
            if fallbacks(&handle, unit) > before {
                return Some(());
            }
            tokio::task::block_in_place(|| sim.stall(Duration::from_millis(400)));
            None
        })
        .await;
        // A poll checks its gap again, and it holds again.
        eventually(LIMIT, "the gap back", || {
            (gap_us(&handle, unit) == Some(held)).then_some(())
        })
        .await;
        stop.cancel();
        let errors = errors_of(tasks).await;
        assert!(errors.is_empty(), "no client error: {errors:?}");
        let to_unit: Vec<Request> = requests(&bus)
            .into_iter()
            .filter(|q| q.unit == unit && q.seq >= stalled_at)
            .collect();
        let miss = to_unit
            .iter()
            .position(|q| !q.answered)
            .expect("the request during the stall missed");
        // After the miss, the first request shorter than the spec was a
        // poll after the gap that had held (not a trial below it, as
        // relearning makes), and it was answered; none before it.
        let short = to_unit[miss + 1..]
            .iter()
            .find(|q| q.silence < SPEC_US - 100)
            .expect("a request after a shorter silence");
        assert!(short.poll && short.answered, "{short:?} in {to_unit:?}");
        assert!(short.silence + 100 >= held, "{short:?}, held {held} us");
        assert_clients_kept_confirmed_gaps(&requests(&bus));
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_and_emergencies_never_use_an_unconfirmed_gap() {
    bounded(WHOLE, async {
        // Clients from the start: while the polls try shorter silences, the
        // clients' requests wait at least their drive's confirmed gap,
        // which never falls below the floor.
        let d = TestDaemon::start(&config("\"auto\"", "", 100)).await;
        let bus = d.plant.buses()[0].clone();
        let handle = bus.handle.clone();
        let stop = CancellationToken::new();
        let (answered, tasks) = clients(&handle, &[1, 2, 3, 4], &stop);
        learned_each(&handle, &[1, 2, 3, 4], 1).await;
        let before = answered.load(Ordering::Relaxed);
        eventually(LIMIT, "reads after learning", || {
            (answered.load(Ordering::Relaxed) > before + 200).then_some(())
        })
        .await;
        stop.cancel();
        let errors = errors_of(tasks).await;
        assert!(errors.is_empty(), "{errors:?}");
        let seen = requests(&bus);
        assert!(
            seen.iter().any(|q| !q.poll && q.silence < SPEC_US),
            "gaps used"
        );
        assert_clients_kept_confirmed_gaps(&seen);
        d.stop().await;
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn spec_leaves_no_silence_shorter_than_t3_5() {
    bounded(WHOLE, async {
        // Fast drives, but the default setting: every silence is the spec's.
        let toml = config("\"spec\"", "", 20).replace("interframe = \"spec\"\n", "");
        let d = TestDaemon::start(&toml).await;
        let bus = d.plant.buses()[0].clone();
        let handle = bus.handle.clone();
        let stop = CancellationToken::new();
        let (answered, tasks) = clients(&handle, &[1, 2, 3, 4], &stop);
        eventually(LIMIT, "reads", || {
            (answered.load(Ordering::Relaxed) > 300).then_some(())
        })
        .await;
        stop.cancel();
        assert!(errors_of(tasks).await.is_empty());
        let seen = requests(&bus);
        assert!(
            seen.len() > 300 && seen.iter().any(|q| q.poll),
            "polls and clients"
        );
        let shortest = seen.iter().map(|q| q.silence).min();
        assert!(shortest >= Some(SPEC_US), "{shortest:?}");
        for unit in 1..=4 {
            assert_eq!(gap_us(&handle, unit), Some(SPEC_US));
        }
        let sim = d.sim().stats();
        assert_eq!((sim.gap_violations, sim.merged_frames), (0, 0), "{sim}");
        d.stop().await;
    })
    .await;
}
