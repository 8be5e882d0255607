//! schemathesis (PyPI) against the OpenAPI document the daemon serves, run
//! on the daemon on the simulator with an admin token: requests generated
//! from the document, valid and invalid, for every operation, checked with
//! every schemathesis check (the exceptions, and why, are in
//! `tests/python/schemathesis.toml`). It must find nothing: no server error,
//! no answer outside the document, no valid request refused, no invalid one
//! accepted, no route that ignores its token.
//!
//! Bounded for CI: `DRIVEGATE_ST_EXAMPLES` examples per operation (default
//! 3) with a fixed seed (`DRIVEGATE_ST_SEED`); run more locally with e.g.
//! `DRIVEGATE_ST_EXAMPLES=100 cargo test --test e2e input::schemathesis`.

use std::path::Path;
use std::time::Duration;

use crate::support::TestDaemon;
use crate::support::input::{ADMIN, config, drives_up_to_32};

fn setting(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The figure before `label` on the summary line of test cases
/// ("922 generated, 922 passed, 26 skipped").
fn figure(output: &str, label: &str) -> Option<u64> {
    let summary = output
        .lines()
        .find(|l| l.contains(" generated, ") && l.contains(" passed"))?;
    summary.split(',').find_map(|part| {
        let (n, what) = part.trim().split_once(' ')?;
        (what.trim() == label).then(|| n.parse().ok()).flatten()
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn schemathesis_finds_nothing_in_the_served_document() {
    let examples = setting("DRIVEGATE_ST_EXAMPLES", 3);
    let seed = setting("DRIVEGATE_ST_SEED", 20261122);
    // A bound for a run that hangs, far above a loaded machine's (121 s
    // beside a CPU hog and the whole suite at 3 examples).
    let limit = Duration::from_secs(300 + 20 * examples);
    tokio::time::timeout(limit, async {
        // Every unit of a scan's default range answers: no silent unit
        // spends the bus's time.
        // schemathesis sends wrong tokens on purpose, more than the pause
        // after token guesses lets through.
        let text = drives_up_to_32(&config("token_guesses = 1000000", "", true, ""));
        let d = TestDaemon::start(&text).await;
        let settings = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/schemathesis.toml");
        // schemathesis keeps a cache and an example database in its working
        // directory: a fresh one each run, so the run is the seed's alone.
        let workdir = tempfile::tempdir().unwrap();
        let mut st = tokio::process::Command::new("st");
        st.arg("--no-color")
            .arg("--config-file")
            .arg(&settings)
            .arg("run")
            .arg(d.url("/openapi.json"))
            .args(["--checks", "all"])
            .args(["--max-examples", &examples.to_string()])
            .args(["--seed", &seed.to_string()])
            .args(["--workers", "1"])
            .env("DRIVEGATE_ST_TOKEN", ADMIN)
            .current_dir(workdir.path())
            .kill_on_drop(true);
        let output = match st.output().await {
            Ok(o) => o,
            // The version scripts/test pins: others may find other things.
            Err(e) => panic!("{}", crate::support::tools::cannot_run("st", &e)),
        };
        let out = format!(
            "{}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
        assert!(
            output.status.success(),
            "schemathesis found problems (seed {seed}):\n{out}"
        );
        let doc = drivegate::api::openapi::document();
        let operations: usize = doc
            .paths
            .paths
            .values()
            .map(|item| {
                let i = serde_json::to_value(item).unwrap();
                ["get", "put", "post", "delete", "patch"]
                    .iter()
                    .filter(|m| i.get(**m).is_some())
                    .count()
            })
            .sum();
        // Three are left out on purpose (see the settings file): the
        // address setting and the two WebSockets.
        let tested = out
            .lines()
            .find_map(|l| l.trim().strip_prefix("Tested: ")?.trim().parse::<usize>().ok());
        assert_eq!(tested, Some(operations - 3), "operations tested:\n{out}");
        let generated = figure(&out, "generated").unwrap_or(0);
        let passed = figure(&out, "passed").unwrap_or(0);
        assert!(generated > 100 && passed == generated, "{out}");
        // The daemon counts no server error either.
        let metrics = d.metrics.render();
        let server_errors: f64 = metrics
            .lines()
            .filter(|l| l.starts_with("drivegate_http_requests_total{") && l.contains("status=\"5"))
            .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
            .sum();
        assert_eq!(server_errors, 0.0, "server errors counted in /metrics");
        println!(
            "schemathesis (seed {seed}, {examples} examples per operation): {} operations, {generated} requests, {passed} passed, 0 failures",
            operations - 3
        );
        d.stop().await;
    })
    .await
    .expect("schemathesis finished in time");
}
