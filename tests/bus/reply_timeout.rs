//! Learned reply timeouts and idle-time probes, end to end on the
//! simulator through a real pty: drives that slow down in the middle of the
//! traffic cost no client an error and their timeout follows; a silent
//! drive's probes wait for the clients except once per longest backoff.
//!
//! Every wait is for an event (a figure in the bus's counters), bounded
//! only against a hang.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::support::{TestDaemon, eventually};
use drivegate::bus::BusHandle;
use drivegate::bus::handle::JobOptions;
use drivegate::drive::{DriveReply, DriveRequest};
use drivegate::sim::FaultRates;
use tokio_util::sync::CancellationToken;

const LIMIT: Duration = Duration::from_secs(60);

fn config(drives: &[u8], bus_keys: &str, silent: &str) -> String {
    let mut toml = format!(
        "[http]\nlisten = \"127.0.0.1:0\"\n[modbus_tcp]\nenabled = false\n\
         [safety]\non_shutdown = \"none\"\n\
         [[bus]]\nname = \"line\"\nport = \"sim\"\n\
         poll_interval_ms = 1000\n{bus_keys}\n\
         [bus.sim]\nturnaround_ms = 0.5\n[bus.sim.faults]\nsilent_units = [{silent}]\n"
    );
    for unit in drives {
        toml.push_str(&format!(
            "[[bus.drive]]\nunit = {unit}\nname = \"d{unit}\"\n"
        ));
    }
    toml
}

/// Clients reading the status of `units` back to back, one each, until
/// `stop`: their answered reads (shared, as they go) and, at the end, every
/// error.
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
                while !stop.is_cancelled() {
                    match bus
                        .execute(unit, &DriveRequest::ReadStatus, JobOptions::default())
                        .await
                    {
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

fn reply_timeout(bus: &BusHandle, unit: u8) -> Option<Duration> {
    bus.stats().drives.get(&unit).map(|t| t.reply_timeout)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drives_that_slow_down_cost_no_client_an_error_and_their_timeout_follows() {
    let units = [1, 2, 3, 4];
    // A ceiling far above the slowed drives: the simulator answers one
    // request at a time, so a slowed reply delays the retries queued
    // behind it, each by as much again.
    let d = TestDaemon::start(&config(
        &units,
        "retries = 3\nresponse_timeout_ms = 1000",
        "",
    ))
    .await;
    let bus = d.plant.buses()[0].handle.clone();
    let stop = CancellationToken::new();
    let (answered, tasks) = clients(&bus, &units, &stop);

    // Learned, far below the ceiling: on a quiet machine a few
    // milliseconds (0.5 ms turnaround + t3.5), more on a loaded one, whose
    // threads answer late now and then.
    let learned = eventually(LIMIT, "every drive's timeout learned", || {
        units
            .iter()
            .map(|&u| reply_timeout(&bus, u).filter(|t| *t < Duration::from_millis(40)))
            .collect::<Option<Vec<_>>>()
            .and_then(|ts| ts.into_iter().max())
    })
    .await;

    // Every drive now answers five times later than the longest timeout
    // learned so far (19.5 ms on a quiet machine): its replies come after
    // the timeouts, and are taken late by a transaction's last attempt
    // (which waits the ceiling) or within a retry's doubled wait.
    let late_ms = (learned.as_secs_f64() * 1000.0 * 5.0).clamp(19.5, 150.0);
    let retries_before = bus.stats().retries;
    d.sim()
        .set_fault_rates(FaultRates {
            late_rate: 1.0,
            late_ms,
            ..FaultRates::default()
        })
        .unwrap();
    let slowed = answered.load(Ordering::Relaxed);
    eventually(
        LIMIT,
        "every drive's timeout above its new turnaround",
        || {
            units
                .iter()
                .all(|&u| {
                    reply_timeout(&bus, u)
                        .is_some_and(|t| t.as_secs_f64() * 1000.0 > late_ms + 1.75)
                })
                .then_some(())
        },
    )
    .await;
    // And it holds: more reads at the new pace. (Until the timeout had
    // followed, a retry could reach a drive before the late reply it owed:
    // the reply was then taken as the retry's, the same request's answer,
    // or discarded, never handed to another request.)
    let followed = answered.load(Ordering::Relaxed);
    eventually(LIMIT, "120 reads of the slowed drives", || {
        (answered.load(Ordering::Relaxed) >= followed + 120).then_some(())
    })
    .await;
    stop.cancel();
    let mut errors = Vec::new();
    for t in tasks {
        errors.extend(t.await.unwrap());
    }
    assert!(errors.is_empty(), "{errors:?}");
    let stats = bus.stats();
    // The drives' timeouts were raised by their replies, and stayed below
    // the ceiling. They followed one of two ways, both without an error: a
    // reply taken after the learned timeout (by the last attempt, which
    // waits the ceiling) is learned at once; or attempts that timed out
    // each doubled the next one's wait until a reply came within it (on a
    // loaded machine, where a late reply more often answers a retry: no
    // clean sample, so none is learned from it, and none is counted late).
    for u in units {
        let t = stats.drives[&u].reply_timeout;
        assert!(t < Duration::from_millis(1000), "unit {u}: {t:?}");
    }
    let late: u64 = units.iter().map(|u| stats.drives[u].late_replies).sum();
    let retried = stats.retries - retries_before;
    assert!(
        late + retried > 0,
        "the slowdown went unnoticed: no reply taken late, no attempt retried"
    );
    eprintln!(
        "{} reads before the slowdown, {} while the timeouts followed: {late} replies taken late, {retried} attempts retried",
        slowed,
        followed - slowed
    );
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_drives_probes_wait_for_the_clients_except_at_the_longest_backoff() {
    // Unit 5 never answers; its backoff starts at 50 ms and is at most
    // 1.5 s. Four clients keep three requests waiting all the time.
    let units = [1, 2, 3, 4];
    let longest = Duration::from_millis(1500);
    let d = TestDaemon::start_no_wait(&config(
        &[1, 2, 3, 4, 5],
        // Three retries: a live drive's reply the machine kept the
        // simulator from sending in time (a loaded machine) costs no client
        // an error. A probe is one attempt whatever the retries.
        "retries = 3\nresponse_timeout_ms = 250\n\
         offline_backoff_ms = 50\noffline_backoff_max_ms = 1500",
        "5",
    ))
    .await;
    let bus = d.plant.buses()[0].handle.clone();
    let stop = CancellationToken::new();
    eventually(LIMIT, "the live drives online", || {
        units
            .iter()
            .all(|&u| bus.drive(u).is_some_and(|s| s.status.is_some()))
            .then_some(())
    })
    .await;
    let (answered, tasks) = clients(&bus, &units, &stop);
    // Its first probe failed: it is backed off.
    eventually(LIMIT, "the silent drive probed", || {
        bus.drive(5)
            .filter(|s| s.consecutive_failures >= 1)
            .map(|s| s.consecutive_failures)
    })
    .await;
    let probes_before = d.sim().stats().unanswered;
    let start = Instant::now();
    let reads_before = answered.load(Ordering::Relaxed);
    // 600 reads: without waiting for the clients, the probes would come
    // after 50, 100, 200, 400, 800 ms, 1.5 s... (six in the first 3 s).
    eventually(LIMIT, "600 reads", || {
        (answered.load(Ordering::Relaxed) >= reads_before + 600).then_some(())
    })
    .await;
    let elapsed = start.elapsed();
    let probes = d.sim().stats().unanswered - probes_before;
    stop.cancel();
    let mut errors = Vec::new();
    for t in tasks {
        errors.extend(t.await.unwrap());
    }
    assert!(errors.is_empty(), "{errors:?}");
    // While clients waited, one probe per longest backoff at most (and
    // one may be under way at the start).
    let allowed = (elapsed.as_secs_f64() / longest.as_secs_f64()).floor() as u64 + 1;
    assert!(
        probes <= allowed,
        "{probes} probes in {elapsed:?} while clients waited (at most {allowed})"
    );
    // Each probe waited the shortest timeout, not the 250 ms ceiling.
    assert!(bus.drive(5).is_some_and(|s| s.status.is_none()));
    d.stop().await;
}
