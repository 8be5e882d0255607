//! Replays the committed fuzz corpus (`fuzz/corpus/<target>/`) through the
//! fuzz targets' bodies, so every `cargo test` re-checks every input the
//! fuzzer found interesting, without the fuzzer.

#![allow(dead_code)]

include!("../../fuzz/targets.rs");

fn replay(target: &str, f: fn(&[u8])) {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target);
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        f(&std::fs::read(&path).unwrap());
        n += 1;
    }
    assert!(n > 0, "the {target} corpus is empty");
}

#[test]
fn rtu_reply_corpus() {
    replay("rtu_reply", rtu_reply);
}

#[test]
fn config_corpus() {
    replay("config", config);
}

#[test]
fn sim_request_corpus() {
    replay("sim_request", sim_request);
}

#[test]
fn mbap_corpus() {
    replay("mbap", mbap);
}

#[test]
fn http_body_corpus() {
    replay("http_body", http_body);
}
