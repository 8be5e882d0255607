//! A test alone in a process of its own, under a plain `cargo test` too
//! (which runs every test of the binary in threads of one process): for a
//! test that measures the whole process (its memory, its file descriptors)
//! or installs the process's one global log subscriber.

use std::process::Command;

/// Set to the test's name in the process that runs it alone.
const ALONE: &str = "DRIVEGATE_TEST_ALONE";

/// Whether the test `name` of the module `module` (`module_path!()`) runs
/// in this process. In the process made for it, true: go on with the test.
/// Elsewhere the binary is run again for that test alone, its output
/// becomes this test's, and this fails if it fails; false: return.
///
/// ```ignore
/// if !alone::here(module_path!(), "a_test_of_the_whole_process") {
///     return;
/// }
/// ```
pub fn here(module: &str, name: &str) -> bool {
    // module_path!() starts with the binary's name.
    let module = module.split_once("::").map_or("", |(_, rest)| rest);
    let test = format!("{module}::{name}");
    if std::env::var_os(ALONE).is_some_and(|v| v == test.as_str()) {
        return true;
    }
    let exe = std::env::current_exe().expect("the test binary's path");
    // The run's choice of output (`cargo test -- --nocapture`) holds there.
    let shown = std::env::args()
        .filter(|a| ["--nocapture", "--no-capture", "--show-output"].contains(&a.as_str()));
    let out = Command::new(exe)
        .args([&test, "--exact", "--test-threads=1"])
        .args(shown)
        .env(ALONE, &test)
        .output()
        .expect("the test binary runs again");
    let stdout = String::from_utf8_lossy(&out.stdout);
    print!("{stdout}");
    eprint!("{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{test}, alone in its process, failed");
    assert!(
        stdout.contains("test result: ok. 1 passed"),
        "no test {test} in this binary: a renamed test passes its new name to alone::here"
    );
    false
}
