//! The package manifest says what the code needs, no more: the oldest Rust
//! it builds with, and only crates the daemon itself uses as dependencies
//! (what only the tests and benchmarks use is a dev-dependency, so it is
//! not built into the daemon); and one binary for the end-to-end tests.

use std::path::Path;

fn manifest() -> toml::Table {
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("Cargo.toml"))
        .expect("Cargo.toml");
    toml::from_str(&text).expect("Cargo.toml parses")
}

fn sources(dir: &Path, out: &mut String) {
    for entry in std::fs::read_dir(dir).expect("source directory") {
        let path = entry.expect("entry").path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push_str(&std::fs::read_to_string(&path).expect("source file"));
        }
    }
}

/// (major, minor) of a version such as "1.91" or "rustc 1.95.0 (...)".
fn major_minor(text: &str) -> (u32, u32) {
    let version = text
        .split_whitespace()
        .find(|w| w.chars().next().is_some_and(|c| c.is_ascii_digit()))
        .expect("a version number");
    let mut parts = version
        .split('.')
        .map(|p| p.parse::<u32>().expect("a number"));
    (parts.next().unwrap(), parts.next().unwrap_or(0))
}

#[test]
fn the_oldest_rust_it_builds_with_is_declared() {
    let package = manifest()["package"].as_table().unwrap().clone();
    let declared = package
        .get("rust-version")
        .and_then(|v| v.as_str())
        .expect("[package] rust-version is declared");
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".to_string());
    let output = std::process::Command::new(rustc)
        .arg("--version")
        .output()
        .expect("rustc runs");
    let running = String::from_utf8_lossy(&output.stdout).to_string();
    assert!(
        major_minor(declared) <= major_minor(&running),
        "rust-version {declared} is newer than the compiler that built the tests ({running})"
    );
    // The edition needs 1.85; the code uses let chains (1.88) and
    // str::floor_char_boundary (1.91).
    assert!(major_minor(declared) >= (1, 91), "{declared}");
}

#[test]
fn every_dependency_is_used_by_the_daemon() {
    let mut src = String::new();
    sources(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"), &mut src);
    let manifest = manifest();
    let dependencies = manifest["dependencies"].as_table().unwrap();
    let unused: Vec<&String> = dependencies
        .keys()
        .filter(|name| {
            let lib = name.replace('-', "_");
            !(src.contains(&format!("{lib}::")) || src.contains(&format!("use {lib}")))
        })
        .collect();
    assert!(
        unused.is_empty(),
        "dependencies the daemon's code never uses (remove them, or make them dev-dependencies if only tests and benchmarks use them): {unused:?}"
    );
}

/// The end-to-end tests are one binary (`tests/main.rs`, a module per
/// area): each test binary links the whole daemon and its dependencies,
/// seconds of a two-core build. Cargo would make a binary of any other
/// `tests/*.rs` or `tests/*/main.rs`.
#[test]
fn the_end_to_end_tests_are_one_binary() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let declared: Vec<String> = manifest()["test"]
        .as_array()
        .expect("[[test]] in Cargo.toml")
        .iter()
        .map(|t| format!("{} {}", t["name"], t["path"]))
        .collect();
    assert_eq!(declared, [r#""e2e" "tests/main.rs""#]);
    let mut more = Vec::new();
    for entry in std::fs::read_dir(root.join("tests")).expect("tests/") {
        let path = entry.expect("entry").path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if path.join("main.rs").is_file() {
            more.push(format!("tests/{name}/main.rs"));
        } else if name.ends_with(".rs") && name != "main.rs" {
            more.push(format!("tests/{name}"));
        }
    }
    assert!(
        more.is_empty(),
        "test binaries besides tests/main.rs: {more:?}; make each a module of an area \
         (tests/<area>/<part>.rs, declared in tests/<area>/mod.rs)"
    );
}
