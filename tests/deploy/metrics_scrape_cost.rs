//! Benchmark (ignored by `cargo test`; it measures, it asserts nothing about
//! time): what a scrape costs and whether scraping slows the bus.
//!
//! ```sh
//! cargo test --release --test e2e deploy::metrics_scrape_cost -- --ignored --nocapture
//! ```
//!
//! With 8 simulated drives polled as fast as the bus allows at 115200 baud,
//! it prints the render time (mean, p50, p99), the exposition's size, and
//! the status polls per second over 3 s without scrapes, then over 3 s while
//! another thread scrapes back to back.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::support::TestDaemon;
use crate::support::config::ConfigBuilder;

fn eight_drives() -> String {
    ConfigBuilder::new()
        .bus("bench", |b| {
            (1..=8).fold(b, |b, unit| b.drive(unit, &format!("drive{unit}")))
        })
        .toml()
}

fn polls(d: &TestDaemon) -> u64 {
    d.plant.buses()[0].handle.stats().polls
}

async fn polls_per_second(d: &TestDaemon, over: Duration) -> f64 {
    let (p0, t0) = (polls(d), Instant::now());
    tokio::time::sleep(over).await;
    (polls(d) - p0) as f64 / t0.elapsed().as_secs_f64()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "benchmark: run with --ignored --nocapture"]
async fn scrape_cost_and_bus_throughput() {
    tokio::time::timeout(Duration::from_secs(60), async {
        let d = TestDaemon::start(&eight_drives()).await;

        let mut times = Vec::with_capacity(1000);
        let mut bytes = 0;
        for _ in 0..1000 {
            let t = Instant::now();
            let text = d.metrics.render();
            times.push(t.elapsed());
            bytes = text.len();
        }
        times.sort();
        let mean = times.iter().sum::<Duration>() / times.len() as u32;
        println!(
            "render, 8 drives: mean {:?}, p50 {:?}, p99 {:?}, {} bytes, {} lines",
            mean,
            times[500],
            times[990],
            bytes,
            d.metrics.render().lines().count()
        );

        let quiet = polls_per_second(&d, Duration::from_secs(3)).await;
        let stop = Arc::new(AtomicBool::new(false));
        let scrapes = Arc::new(AtomicU64::new(0));
        let scraper = {
            let (metrics, stop, scrapes) = (d.metrics.clone(), stop.clone(), scrapes.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    std::hint::black_box(metrics.render());
                    scrapes.fetch_add(1, Ordering::Relaxed);
                }
            })
        };
        let busy = polls_per_second(&d, Duration::from_secs(3)).await;
        stop.store(true, Ordering::Relaxed);
        scraper.join().unwrap();
        println!(
            "status polls/s: {quiet:.0} without scrapes, {busy:.0} while scraping back to back \
             ({:.0} scrapes/s)",
            scrapes.load(Ordering::Relaxed) as f64 / 3.0
        );
        println!(
            "gap violations seen by the simulator: {}",
            d.sim().stats().gap_violations
        );
        d.stop().await;
    })
    .await
    .expect("benchmark finished in time");
}
