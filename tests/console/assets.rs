//! The console's files as the daemon serves them: every file under `web/`
//! is built into the binary, the vendored uPlot is the published one
//! (checked against its manifest), the page has no inline script, names
//! no other host, and is served with its content type, a
//! Content-Security-Policy and an ETag that a browser revalidates.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::support::{FOUR_DRIVES, TestDaemon};
use drivegate::console::ASSETS;
use sha2::Digest;

fn web() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("web")
}

fn files_under(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files_under(&path, out);
        } else {
            out.push(path);
        }
    }
}

/// The path a file under `web/` is served at, under `/console/`.
fn served_path(file: &Path) -> String {
    let rel = file
        .strip_prefix(web())
        .unwrap()
        .to_string_lossy()
        .to_string();
    rel.strip_prefix("console/")
        .map_or(rel.clone(), str::to_string)
}

#[test]
fn every_file_under_web_is_in_the_binary_as_it_is_on_disk() {
    let mut files = Vec::new();
    files_under(&web(), &mut files);
    let on_disk: BTreeSet<String> = files.iter().map(|f| served_path(f)).collect();
    let built: BTreeSet<String> = ASSETS.iter().map(|a| a.path.to_string()).collect();
    assert_eq!(on_disk, built, "web/ and drivegate::console::ASSETS differ");
    for file in &files {
        let asset = ASSETS.iter().find(|a| a.path == served_path(file)).unwrap();
        assert_eq!(
            asset.bytes,
            std::fs::read(file).unwrap().as_slice(),
            "{}",
            file.display()
        );
    }
}

#[test]
fn the_vendored_uplot_matches_its_manifest() {
    let dir = web().join("vendor/uplot");
    let manifest = std::fs::read_to_string(dir.join("MANIFEST")).unwrap();
    assert!(
        manifest.lines().any(|l| l == "version 1.6.32"),
        "{manifest}"
    );
    let mut checked = BTreeSet::new();
    for line in manifest.lines().filter(|l| l.starts_with("sha256 ")) {
        let mut parts = line.split_whitespace().skip(1);
        let (hash, name) = (parts.next().unwrap(), parts.next().unwrap());
        let bytes = std::fs::read(dir.join(name)).unwrap();
        let actual: String = sha2::Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        assert_eq!(actual, hash, "{name} is not the file of uplot 1.6.32");
        checked.insert(name.to_string());
    }
    let mut present = BTreeSet::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().to_string();
        if name != "MANIFEST" {
            present.insert(name);
        }
    }
    assert_eq!(checked, present, "every vendored file is in the manifest");
    assert!(checked.contains("LICENSE"));
}

#[test]
fn the_page_has_no_inline_script_and_names_no_other_host() {
    let html = std::fs::read_to_string(web().join("console/index.html")).unwrap();
    for (i, _) in html.match_indices("<script") {
        let tag = &html[i..i + html[i..].find('>').unwrap()];
        assert!(
            tag.contains(" src=\"/console/"),
            "inline or foreign script: {tag}"
        );
    }
    let lower = html.to_lowercase();
    for needle in [
        " onclick=",
        " onload=",
        " onerror=",
        " style=",
        "javascript:",
    ] {
        assert!(!lower.contains(needle), "index.html has {needle}");
    }
    let mut files = Vec::new();
    files_under(&web().join("console"), &mut files);
    for file in files {
        let text = std::fs::read_to_string(&file).unwrap();
        for needle in [
            "http://",
            "https://",
            "//cdn",
            "fonts.googleapis",
            "@import",
            "eval(",
            "new Function",
        ] {
            let allowed =
                needle == "http://" && text.contains("xmlns=\"http://www.w3.org/2000/svg\"");
            assert!(
                allowed || !text.contains(needle),
                "{} contains {needle}",
                file.display()
            );
        }
    }
}

#[test]
fn every_page_module_is_in_the_navigation() {
    let app = std::fs::read_to_string(web().join("console/app.js")).unwrap();
    for entry in std::fs::read_dir(web().join("console/pages")).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().to_string();
        assert!(
            app.contains(&format!("from './pages/{name}'")),
            "pages/{name} is not imported by app.js"
        );
    }
}

/// Every picture in docs/ is taken by a test of this binary through
/// `browser::picture` (so it is retaken, and what it shows was checked,
/// at each `DRIVEGATE_SCREENSHOTS=docs cargo test --test e2e console::`), and
/// every picture the docs show is there.
#[test]
fn every_picture_of_the_docs_is_taken_by_a_test() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut tests = String::new();
    for entry in std::fs::read_dir(root.join("tests/console")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "rs") {
            tests.push_str(&std::fs::read_to_string(path).unwrap());
        }
    }
    // The name of each picture a `picture(page, "name", ...)` call takes.
    let mut taken = Vec::new();
    for (i, _) in tests.match_indices("picture(") {
        let call = &tests[i..tests[i..].find(".await").map_or(tests.len(), |e| i + e)];
        if let Some(name) = call.split('"').nth(1) {
            taken.push(name.to_string());
        }
    }
    let mut docs_text = std::fs::read_to_string(root.join("README.md")).unwrap();
    let mut untaken = Vec::new();
    for entry in std::fs::read_dir(root.join("docs")).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().to_string();
        if name.ends_with(".png") && !taken.contains(&name) {
            untaken.push(name.clone());
        }
        if name.ends_with(".md") {
            docs_text.push_str(&std::fs::read_to_string(root.join("docs").join(&name)).unwrap());
        }
    }
    assert!(
        untaken.is_empty(),
        "pictures in docs/ no test takes: {untaken:?}"
    );
    for (i, _) in docs_text.match_indices(".png)") {
        let start = docs_text[..i].rfind('(').unwrap() + 1;
        let shown = docs_text[start..i + 4].trim_start_matches("docs/");
        assert!(
            root.join("docs").join(shown).is_file(),
            "the docs show {shown}, which is not in docs/"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn served_with_types_policy_and_revalidation() {
    let daemon = TestDaemon::start(FOUR_DRIVES).await;
    let client = reqwest::Client::new();
    let page = client.get(daemon.url("/")).send().await.unwrap();
    assert_eq!(page.status(), 200);
    let h = page.headers().clone();
    assert_eq!(h["content-type"], "text/html; charset=utf-8");
    let csp = h["content-security-policy"].to_str().unwrap();
    let host = daemon.http.to_string();
    for part in [
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        &format!("connect-src 'self' ws://{host} wss://{host}"),
        "frame-ancestors 'none'",
    ] {
        assert!(csp.contains(part), "{csp} lacks {part}");
    }
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"));
    assert_eq!(h["x-content-type-options"], "nosniff");
    assert_eq!(h["cache-control"], "no-cache");
    let etag = h["etag"].clone();
    let body = page.text().await.unwrap();
    assert!(body.contains("<title>drivegate</title>"));

    // The browser's copy is current: 304, no body.
    let again = client
        .get(daemon.url("/"))
        .header("if-none-match", etag.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(again.status(), 304);
    assert_eq!(again.headers()["etag"], etag);
    assert!(again.bytes().await.unwrap().is_empty());

    for (path, kind) in [
        ("/console/app.js", "text/javascript; charset=utf-8"),
        ("/console/pages/drive.js", "text/javascript; charset=utf-8"),
        ("/console/style.css", "text/css; charset=utf-8"),
        ("/console/icon.svg", "image/svg+xml"),
        (
            "/console/vendor/uplot/uPlot.iife.min.js",
            "text/javascript; charset=utf-8",
        ),
        ("/console/vendor/uplot/LICENSE", "text/plain; charset=utf-8"),
    ] {
        let r = client.get(daemon.url(path)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{path}");
        assert_eq!(r.headers()["content-type"], kind, "{path}");
        assert!(r.headers().contains_key("etag"), "{path}");
    }
    // Unknown files are a problem document, like every other 404.
    let missing = client
        .get(daemon.url("/console/nope.js"))
        .send()
        .await
        .unwrap();
    assert_eq!(missing.status(), 404);
    assert_eq!(
        missing.headers()["content-type"],
        "application/problem+json"
    );
    let escape = client
        .get(daemon.url("/console/../Cargo.toml"))
        .send()
        .await
        .unwrap();
    assert_eq!(escape.status(), 404);
    daemon.stop().await;
}
