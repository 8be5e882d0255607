//! The gateway's own pages in a real browser, one daemon and one page
//! walking through a first day's work: a typo in the configuration caught
//! at its line as it is typed; a drive renamed and applied while a drive
//! of the other bus turns on (and keeps turning); the page's next change
//! refused after another admin changed the file, naming that change; an
//! API token made,
//! copied, used and revoked; a refused OPC UA client (asyncua) trusted
//! from the Certificates page and then connecting, and its certificate,
//! which expires within 30 days, an alarm. The time it took is printed.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

use super::browser::{LONG, assert_clean, open, picture, rest, text};
use super::harness::cdp::{Browser, Page};
use crate::support::config::ConfigBuilder;
use crate::support::opcua::{application_cert_for, host_name};
use crate::support::{TestDaemon, bounded, eventually};
use drivegate::plant::SimRef;

const LIMIT: Duration = Duration::from_secs(240);
const ADMIN: &str = "gateway-admin-6e02b1c7";
const SECOND: &str = "gateway-second-93d4a0f5";

/// The plant: the belt turns on gw1 while gw2's press is renamed.
fn plant(pki: &Path) -> String {
    let toml = ConfigBuilder::new()
        .bus("gw1", |b| b.drive(1, "gw_belt").drive(2, "gw_lift"))
        .bus("gw2", |b| b.drive(1, "gw_press").drive(2, "gw_saw"))
        .http_token("gwadmin", "admin", ADMIN)
        .http_token("gwsecond", "admin", SECOND)
        .section("safety", "lease_max_ms = 600000")
        .section(
            "opcua",
            &format!(
                "listen = \"127.0.0.1:0\"\npki_dir = \"{}\"\nsecurity = [\"none\", \"basic256sha256\"]",
                pki.display()
            ),
        )
        .toml();
    format!("# The gateway of the packing line: comments are kept by every change.\n{toml}")
}

/// `dir/pki` with the server's own certificate, valid a year (made by
/// openssl: the daemon's own RSA key generation is slow in a debug build).
fn server_pki(dir: &Path) -> PathBuf {
    let pki = dir.join("pki");
    for sub in ["own", "private"] {
        std::fs::create_dir_all(pki.join(sub)).unwrap();
    }
    let uri = format!("urn:{}:drivegate", host_name());
    application_cert_for(dir, "server", &uri, 365);
    std::fs::rename(dir.join("server.der"), pki.join("own/cert.der")).unwrap();
    std::fs::rename(dir.join("server-key.pem"), pki.join("private/private.pem")).unwrap();
    pki
}

/// Replaces the first `from` in the editor by `to`, as typing does (the
/// selection over it, then the text inserted: one input event).
async fn type_over(page: &Page, from: &str, to: &str) {
    let at = page
        .eval(&format!(
            "(() => {{ const t = document.querySelector('[data-field=config-text]'); \
             const i = t.value.indexOf({from}); t.focus(); t.setSelectionRange(i, i + {len}); return i; }})()",
            from = serde_json::to_string(from).unwrap(),
            len = from.chars().count()
        ))
        .await;
    assert!(at.as_i64().unwrap() >= 0, "{from:?} is not in the editor");
    page.call("Input.insertText", json!({ "text": to })).await;
}

/// Waits until the editor's check says `state` (`good` or `bad`).
async fn checked(page: &Page, state: &str) -> String {
    page.wait_for(
        &format!(
            "(() => {{ const s = document.querySelector('[data-check=status]'); \
             return s && s.classList.contains('{state}') ? s.textContent : null; }})()"
        ),
        LONG,
        &format!("the check saying {state}"),
    )
    .await
    .as_str()
    .unwrap()
    .to_string()
}

/// Confirms the open dialog, returning its text.
async fn confirm(page: &Page) -> String {
    page.wait_for(
        "document.getElementById('dialog').open",
        LONG,
        "the confirmation",
    )
    .await;
    let said = text(page, "#dialog").await;
    page.click("#dialog button[value=ok]").await;
    said
}

/// The belt's speed on its simulator, rpm.
fn belt_rpm(d: &TestDaemon) -> Option<f64> {
    let bus = d
        .plant
        .buses()
        .into_iter()
        .find(|b| b.handle.name() == "gw1")?;
    SimRef::of(bus)?.drive(1).map(|m| m.speed_rpm)
}

/// asyncua's `secure` scenario with the client certificate in `dir`: the
/// session's status (`Good` when it was served).
async fn secure_session(url: &str, dir: &Path) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/opcua_client.py");
    let out = tokio::process::Command::new("python3")
        .arg(script)
        .args([
            url,
            "secure",
            "--drive",
            "gw_belt",
            "--policy",
            "basic256sha256",
            "--cert",
        ])
        .arg(dir.join("scada.der"))
        .arg("--key")
        .arg(dir.join("scada-key.pem"))
        .output()
        .await
        .unwrap_or_else(|e| panic!("{}", crate::support::tools::cannot_run("asyncua", &e)));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .find(|v| v["step"] == "secure")
        .map_or_else(
            || "no answer".to_string(),
            |v| v["status"].as_str().unwrap_or("").to_string(),
        )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_first_day_of_configuration_certificates_and_tokens_from_the_console() {
    bounded(LIMIT, async {
        let t0 = Instant::now();
        let dir = tempfile::tempdir().unwrap();
        let pki = server_pki(dir.path());
        let path = dir.path().join("drivegate.toml");
        let original = plant(&pki);
        let d = TestDaemon::reloadable_at(&path, &original).await;
        // The belt turns, leased for ten minutes, on gw1.
        for (method, route, body) in [
            ("POST", "/api/v1/drives/gw_belt/commands/activate", None),
            ("PUT", "/api/v1/drives/gw_belt/mode", Some(json!({"mode": "speed"}))),
            (
                "PUT",
                "/api/v1/drives/gw_belt/setpoint",
                Some(json!({"speed_rpm": 100, "lease_ms": 600000})),
            ),
        ] {
            let (status, body) = rest(&d, Some(ADMIN), method, route, body).await;
            assert_eq!(status, 200, "{route}: {body}");
        }
        let turning = |d: &TestDaemon| belt_rpm(d).is_some_and(|r| (r - 100.0).abs() <= 2.0);
        eventually(LONG, "the belt turning", || turning(&d).then_some(())).await;

        let browser = Browser::start(&[]).await;
        let page = open(&browser, &d.url(""), "/config", Some(ADMIN)).await;
        page.wait_for(
            "document.querySelector('[data-field=config-text]').value.startsWith('# The gateway')",
            LONG,
            "the file in the editor",
        )
        .await;
        checked(&page, "good").await;

        // A typo, caught as it is typed, at its line.
        type_over(&page, "port = \"sim\"", "prot = \"sim\"").await;
        let said = checked(&page, "bad").await;
        assert!(said.starts_with("One problem"), "{said}");
        let line = original.lines().position(|l| l.starts_with("port")).unwrap() + 1;
        let marked = page
            .wait_for(
                "(() => { const m = document.querySelector('.gutter .bad'); return m ? m.dataset.line : null; })()",
                LONG,
                "the line marked",
            )
            .await;
        assert_eq!(marked, json!(line.to_string()));
        let remark = text(&page, "[data-check=remarks] li.bad").await;
        assert!(
            remark.starts_with(&format!("Error at line {line}, column 1:")) && remark.contains("prot"),
            "{remark}"
        );
        assert_eq!(
            page.eval("document.querySelector('[data-action=apply]').disabled").await,
            json!(true)
        );
        page.eval("window.scrollTo(0, 0)").await;
        picture(&page, "console-config-typo.png", true).await;
        page.click("[data-action=revert]").await;
        checked(&page, "good").await;

        // The press renamed: its lines and what it does, then applied
        // while the belt turns.
        type_over(&page, "name = \"gw_press\"", "name = \"gw_stamp\"").await;
        checked(&page, "good").await;
        page.wait_for(
            "document.querySelector('[data-field=changes]').textContent.includes('gw_stamp')",
            LONG,
            "what Apply does",
        )
        .await;
        let diff = text(&page, "[data-field=diff]").await;
        assert!(
            diff.contains("− name = \"gw_press\"") && diff.contains("+ name = \"gw_stamp\""),
            "{diff}"
        );
        page.eval("window.scrollTo(0, 0)").await;
        picture(&page, "console-config-diff.png", true).await;
        page.click("[data-action=apply]").await;
        let asked = confirm(&page).await;
        assert!(asked.contains("gw_stamp"), "{asked}");
        let answer = page
            .wait_for(
                "(() => { const r = document.querySelector('[data-result=reload]'); return r ? r.textContent : null; })()",
                LONG,
                "the reload's answer",
            )
            .await;
        let answer = answer.as_str().unwrap();
        assert!(answer.contains("gw_stamp") && answer.contains("gw_press"), "{answer}");
        assert!(turning(&d), "the belt stopped: {:?} rpm", belt_rpm(&d));
        let on_disk = std::fs::read_to_string(&path).unwrap();
        assert!(on_disk.contains("name = \"gw_stamp\"") && on_disk.starts_with("# The gateway"));
        assert!(dir.path().join("drivegate.toml.1").is_file());
        eventually(LONG, "the stamp in the page's drives", || {
            d.plant.now().drives().any(|x| x.name == "gw_stamp").then_some(())
        })
        .await;
        // The file read again after the reload: nothing left to apply.
        page.wait_for(
            "(() => { const s = document.querySelector('[data-check=status]'); \
             return s.classList.contains('good') && s.textContent.endsWith('No edits yet.'); })()",
            LONG,
            "the file read again",
        )
        .await;
        let note = text(&page, ".config-page > .note").await;
        assert!(note.starts_with("written and reloaded"), "{note}");
        page.eval("window.scrollTo(0, 0)").await;
        picture(&page, "console-config-applied.png", true).await;

        // A second admin changes the file meanwhile; this page's next
        // change is refused, naming it.
        let (file, tag) = {
            let r = reqwest::Client::new()
                .get(d.url("/api/v1/config/file"))
                .bearer_auth(SECOND)
                .send()
                .await
                .unwrap();
            let tag = r.headers()["etag"].to_str().unwrap().to_string();
            (r.json::<Value>().await.unwrap(), tag)
        };
        let theirs = file["text"].as_str().unwrap().replace("name = \"gw_saw\"", "name = \"gw_cutter\"");
        let status = reqwest::Client::new()
            .put(d.url("/api/v1/config/file"))
            .bearer_auth(SECOND)
            .header("If-Match", tag)
            .json(&json!({ "text": theirs }))
            .send()
            .await
            .unwrap()
            .status();
        assert_eq!(status, 200);
        type_over(&page, "name = \"gw_lift\"", "name = \"gw_hoist\"").await;
        checked(&page, "good").await;
        page.click("[data-action=apply]").await;
        confirm(&page).await;
        let refused = page
            .wait_for(
                "(() => { const n = document.querySelector('.config-page .note.fail'); return n ? n.textContent : null; })()",
                LONG,
                "the refusal",
            )
            .await;
        let refused = refused.as_str().unwrap();
        assert!(
            refused.contains("http gwsecond")
                && refused.contains("name = \"gw_saw\" became name = \"gw_cutter\""),
            "{refused}"
        );
        assert!(!std::fs::read_to_string(&path).unwrap().contains("gw_hoist"));
        page.eval("window.scrollTo(0, 0)").await;
        picture(&page, "console-config-conflict.png", true).await;
        assert!(turning(&d), "the belt stopped: {:?} rpm", belt_rpm(&d));

        // A token made, shown once, used, and revoked.
        page.eval("location.hash = '#/tokens'").await;
        page.wait_for("!!document.querySelector('tr[data-token=gwadmin]')", LONG, "the tokens")
            .await;
        page.fill("[data-field=token-name]", "gw_scada").await;
        page.eval("(() => { const s = document.querySelector('[data-field=token-role]'); s.value = 'operator'; s.dispatchEvent(new Event('change')); })()")
            .await;
        let before = text(&page, "[data-field=consequence]").await;
        assert!(before.contains("shown once"), "{before}");
        page.click("[data-action=make-token]").await;
        let secret = page
            .wait_for(
                "(() => { const f = document.querySelector('[data-field=new-token]'); return f ? f.value : null; })()",
                LONG,
                "the new token",
            )
            .await;
        let secret = secret.as_str().unwrap().to_string();
        assert_eq!(secret.len(), 64);
        page.click("[data-action=copy-token]").await;
        let (status, me) = rest(&d, Some(&secret), "GET", "/api/v1/whoami", None).await;
        assert_eq!((status, &me["who"], &me["role"]), (200, &json!("gw_scada"), &json!("operator")));
        // Its last use, once the list is read again.
        page.eval("location.hash = '#/config'").await;
        page.eval("location.hash = '#/tokens'").await;
        page.wait_for(
            "(() => { const c = document.querySelector('tr[data-token=gw_scada] [data-field=last-used]'); return !!c && c.textContent !== 'never'; })()",
            LONG,
            "the token's last use",
        )
        .await;
        picture(&page, "console-tokens.png", false).await;
        page.click("button[data-revoke=gw_scada]").await;
        let asked = confirm(&page).await;
        assert!(asked.contains("gw_scada") && asked.contains("refused from the next request"), "{asked}");
        page.wait_for("!document.querySelector('tr[data-token=gw_scada]')", LONG, "the token gone")
            .await;
        let (status, _) = rest(&d, Some(&secret), "GET", "/api/v1/whoami", None).await;
        assert_eq!(status, 401);

        // An OPC UA client refused, trusted from the page, then served.
        let url = format!(
            "opc.tcp://127.0.0.1:{}/",
            d.faces_addresses().await.opcua.unwrap().port()
        );
        application_cert_for(dir.path(), "scada", "urn:packing:scada", 30);
        assert_ne!(secure_session(&url, dir.path()).await, "Good");
        let rejected = pki.join("rejected/certs");
        eventually(LONG, "the certificate in rejected/certs", || {
            std::fs::read_dir(&rejected).ok()?.flatten().next().map(|_| ())
        })
        .await;
        let thumbprint = {
            let der = std::fs::read(dir.path().join("scada.der")).unwrap();
            drivegate::certificate::read(&der).unwrap().thumbprint
        };
        page.eval("location.hash = '#/certificates'").await;
        let row = format!("tr[data-place=opcua-rejected][data-thumbprint='{thumbprint}']");
        page.wait_for(&format!("!!document.querySelector(\"{row}\")"), LONG, "the refused client")
            .await;
        let server = text(&page, "[data-group=opcua-server] tbody").await;
        assert!(server.contains(&format!("urn:{}:drivegate", host_name())), "{server}");
        page.click(&format!("{row} button[data-trust]")).await;
        let asked = confirm(&page).await;
        let pairs: Vec<String> = thumbprint.as_bytes().chunks(2).map(|c| String::from_utf8_lossy(c).into_owned()).collect();
        assert!(asked.contains(&pairs.join(":")) && asked.contains("urn:packing:scada"), "{asked}");
        page.wait_for(
            &format!("!!document.querySelector(\"tr[data-place=opcua-trusted][data-thumbprint='{thumbprint}']\")"),
            LONG,
            "the client trusted",
        )
        .await;
        let t = Instant::now();
        loop {
            if secure_session(&url, dir.path()).await == "Good" {
                break;
            }
            assert!(t.elapsed() < LONG, "the trusted client is still refused");
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
        // It expires within 30 days: an alarm, in the banner.
        page.wait_for(
            "(() => { const b = document.getElementById('alarm-banner'); return !b.hidden && b.textContent.includes('certificate expiring'); })()",
            LONG,
            "the certificate's alarm",
        )
        .await;
        picture(&page, "console-certificates.png", true).await;
        assert!(turning(&d), "the belt stopped: {:?} rpm", belt_rpm(&d));
        assert_clean(&page, &d.url(""));
        println!("the console's first day took {:.1} s", t0.elapsed().as_secs_f64());
        browser.stop().await;
        d.stop().await;
    })
    .await;
}
