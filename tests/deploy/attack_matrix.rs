//! The attack matrix of `docs/security.md` against the tests: every cell
//! names tests that exist (as test functions, where the cell says) or says
//! with `n/a:` why the attack does not apply, so the table cannot rot as
//! tests are renamed, moved or removed.

use std::path::Path;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The faces, in the table's order.
const FACES: [&str; 8] = [
    "HTTP",
    "WebSocket",
    "console",
    "Modbus TCP",
    "Modbus/TCP Security",
    "MQTT Sparkplug",
    "MQTT JSON",
    "OPC UA",
];

/// The attack classes, in the table's order.
const CLASSES: [&str; 9] = [
    "role",
    "clear",
    "lockout",
    "connections",
    "memory",
    "replay",
    "malformed",
    "oversized",
    "state",
];

/// The rows of the table between the page's markers, each split in cells.
fn rows(page: &str) -> Vec<Vec<String>> {
    let start = page
        .find("<!-- attack matrix: start -->")
        .expect("docs/security.md has the attack matrix's start marker");
    let end = page
        .find("<!-- attack matrix: end -->")
        .expect("docs/security.md has the attack matrix's end marker");
    page[start..end]
        .lines()
        .filter(|l| l.starts_with('|'))
        .map(|l| {
            l.trim()
                .trim_matches('|')
                .split(" | ")
                .map(|c| c.trim().to_string())
                .collect()
        })
        .collect()
}

/// The file a reference's test is in, and the test's name:
/// `area/part::name` in `tests/area/part.rs` (or its `mod.rs`),
/// `area::name` in `tests/area/mod.rs`, `src/file.rs::name` there.
fn resolve(reference: &str) -> Option<(std::path::PathBuf, &str)> {
    let (path, name) = reference.rsplit_once("::")?;
    let ident = |s: &str| {
        !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
    };
    if !ident(name) {
        return None;
    }
    let root = Path::new(ROOT);
    if path.starts_with("src/") && path.ends_with(".rs") {
        return Some((root.join(path), name));
    }
    let parts: Vec<&str> = path.split('/').collect();
    if !parts.iter().all(|p| ident(p)) {
        return None;
    }
    let file = match parts.as_slice() {
        [area] => root.join("tests").join(area).join("mod.rs"),
        [area, part] => {
            let flat = root.join("tests").join(area).join(format!("{part}.rs"));
            if flat.exists() {
                flat
            } else {
                root.join("tests").join(area).join(part).join("mod.rs")
            }
        }
        _ => return None,
    };
    Some((file, name))
}

/// True when `source` has a test function `name`: `fn name(` with a test
/// attribute among the lines just above it.
fn has_test(source: &str, name: &str) -> bool {
    let lines: Vec<&str> = source.lines().collect();
    let signature = format!("fn {name}(");
    lines.iter().enumerate().any(|(i, line)| {
        line.contains(&signature)
            && lines[i.saturating_sub(4)..i]
                .iter()
                .map(|l| l.trim_start())
                .any(|l| l.starts_with("#[test]") || l.starts_with("#[tokio::test"))
    })
}

/// What is wrong with one cell, if anything.
fn check_cell(cell: &str) -> Result<usize, String> {
    let spans: Vec<&str> = cell.split('`').skip(1).step_by(2).collect();
    let mut tests = 0;
    for span in spans {
        if !span.contains("::") {
            continue;
        }
        let (file, name) = resolve(span).ok_or_else(|| format!("`{span}` is no test reference"))?;
        let source = std::fs::read_to_string(&file)
            .map_err(|e| format!("`{span}`: {}: {e}", file.display()))?;
        if !has_test(&source, name) {
            return Err(format!(
                "`{span}`: {} has no test function {name}",
                file.display()
            ));
        }
        tests += 1;
    }
    if tests == 0 {
        let reason = cell
            .strip_prefix("n/a:")
            .ok_or_else(|| format!("\"{cell}\" names no test and gives no n/a: reason"))?;
        if reason.split_whitespace().count() < 4 {
            return Err(format!("\"{cell}\": say why in a few words"));
        }
    }
    Ok(tests)
}

#[test]
fn every_cell_of_the_attack_matrix_names_existing_tests_or_says_why_not() {
    let page = std::fs::read_to_string(Path::new(ROOT).join("docs/security.md")).unwrap();
    let rows = rows(&page);
    let (head, body) = rows.split_first().expect("the matrix has a header");
    let classes: Vec<&str> = head.iter().skip(1).map(String::as_str).collect();
    assert_eq!(classes, CLASSES, "the matrix's columns");
    let body: Vec<&Vec<String>> = body.iter().filter(|r| !r[0].starts_with("---")).collect();
    let faces: Vec<&str> = body.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(faces, FACES, "the matrix's rows");
    let mut problems = Vec::new();
    let mut tests = 0;
    for row in body {
        assert_eq!(row.len(), 1 + CLASSES.len(), "the cells of {}", row[0]);
        for (class, cell) in CLASSES.iter().zip(&row[1..]) {
            match check_cell(cell) {
                Ok(n) => tests += n,
                Err(why) => problems.push(format!("{} x {class}: {why}", row[0])),
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    assert!(tests > 60, "{tests} test references");
}

#[test]
fn the_matrix_check_tells_a_test_from_a_reason() {
    assert_eq!(
        check_cell("`deploy/attack_matrix::the_matrix_check_tells_a_test_from_a_reason`"),
        Ok(1)
    );
    assert_eq!(
        check_cell("`src/control/throttle.rs::the_table_is_bounded`, and words"),
        Ok(1)
    );
    // A helper is not a test; a test that is not there, nor a file.
    assert!(check_cell("`deploy/attack_matrix::check_cell`").is_err());
    assert!(check_cell("`deploy/attack_matrix::no_such_test`").is_err());
    assert!(check_cell("`deploy/no_such_part::a_test`").is_err());
    // Words without a test are a reason only when they say so, and why.
    assert!(check_cell("n/a: the face has no such thing to attack").is_ok());
    assert!(check_cell("n/a: no").is_err());
    assert!(check_cell("covered elsewhere").is_err());
    assert!(check_cell("").is_err());
}
