//! The configuration file through the API (`/api/v1/config/file`,
//! `/config/check`, `/tokens`): admins only, and never from another
//! site's page; a typo placed at its line and column; a change made on a
//! version of the file (`If-Match`), written whole with the previous
//! version kept with its mode, reloaded and audited with its lines; a
//! second admin's change on the old version refused, naming the first's;
//! an API token made, used, listed with its last use and revoked through
//! the file; a file drivegate may not write left as it was, the change
//! offered instead.

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::time::Duration;

use serde_json::{Value, json};

use crate::support::api::{Api, Reply};
use crate::support::config::ConfigBuilder;
use crate::support::logs::{capture_logs, log_text};
use crate::support::{TestDaemon, bounded};

const LIMIT: Duration = Duration::from_secs(90);
const ADMIN: &str = "cfgfile-admin-5d21a9";
const SECOND: &str = "cfgfile-second-8b04e7";
const OPERATOR: &str = "cfgfile-panel-31c6f0";

/// A plant of its own (its names are this file's: the log is shared).
fn plant() -> String {
    let toml = ConfigBuilder::new()
        .bus("cfgline", |b| b.drive(1, "cfg_belt").drive(2, "cfg_press"))
        .http_token("cfgadmin", "admin", ADMIN)
        .http_token("cfgsecond", "admin", SECOND)
        .http_token("cfgpanel", "operator", OPERATOR)
        .toml();
    format!("# The cfgline's configuration: kept by every change.\n{toml}")
}

async fn read(api: &Api) -> (Value, String) {
    let reply = api.get("/api/v1/config/file").await;
    let etag = header(&reply, "etag");
    (reply.expect(200), etag)
}

fn header(reply: &Reply, name: &str) -> String {
    reply
        .headers
        .get(name)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string()
}

async fn put(api: &Api, text: &str, if_match: Option<&str>, origin: Option<&str>) -> Reply {
    let url = api.url("/api/v1/config/file");
    let body = json!({ "text": text });
    api.raw(|c| {
        let mut r = c.put(url).json(&body);
        if let Some(m) = if_match {
            r = r.header("If-Match", m);
        }
        if let Some(o) = origin {
            r = r.header("Origin", o);
        }
        r
    })
    .await
}

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o7777
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admins_change_the_file_on_the_version_they_read_and_a_stale_change_names_the_other() {
    capture_logs();
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        let original = plant();
        let d = TestDaemon::reloadable_at(&path, &original).await;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o640)).unwrap();
        let admin = Api::new(d.http, Some(ADMIN));
        let second = admin.with_token(Some(SECOND));
        let operator = admin.with_token(Some(OPERATOR));

        // An operator may not read, check or change the file, nor its tokens.
        operator
            .get("/api/v1/config/file")
            .await
            .expect_problem(403, "forbidden");
        operator
            .post("/api/v1/config/check", json!({"text": original}))
            .await
            .expect_problem(403, "forbidden");
        put(&operator, &original, Some("\"x\""), None)
            .await
            .expect_problem(403, "forbidden");
        operator
            .get("/api/v1/tokens")
            .await
            .expect_problem(403, "forbidden");

        // The file with its comments, and its version.
        let (file, etag) = read(&admin).await;
        assert_eq!(file["text"], original.as_str());
        assert_eq!(etag, format!("\"{}\"", file["sha256"].as_str().unwrap()));
        assert_eq!(
            (&file["writable"], &file["running"]),
            (&json!(true), &json!(true))
        );
        assert_eq!(file["generations"], json!([]));

        // A typo, at its line and column, in check-config's words.
        let typo = original.replacen("port = \"sim\"", "prot = \"sim\"", 1);
        let line = typo.lines().position(|l| l.starts_with("prot")).unwrap() + 1;
        let checked = admin
            .post("/api/v1/config/check", json!({"text": typo}))
            .await
            .expect(200);
        assert_eq!(checked["valid"], false, "{checked:#}");
        let problem = &checked["problems"][0];
        assert_eq!(
            (problem["line"].as_u64(), problem["column"].as_u64()),
            (Some(line as u64), Some(1)),
            "{checked:#}"
        );
        assert!(
            problem["message"].as_str().unwrap().contains("prot"),
            "{problem}"
        );

        // A rename: valid, its lines and what it does in the plant's words.
        let renamed = original.replace("name = \"cfg_press\"", "name = \"cfg_saw\"");
        let checked = admin
            .post("/api/v1/config/check", json!({"text": renamed}))
            .await
            .expect(200);
        assert_eq!(checked["valid"], true, "{checked:#}");
        let changes = checked["changes"].to_string();
        assert!(
            changes.contains("cfg_saw") && changes.contains("cfg_press"),
            "{changes}"
        );
        let lines: Vec<&Value> = checked["diff"][0]["lines"]
            .as_array()
            .unwrap()
            .iter()
            .collect();
        assert!(
            lines
                .iter()
                .any(|l| l["op"] == "removed" && l["text"] == "name = \"cfg_press\""),
            "{checked:#}"
        );
        assert!(
            lines
                .iter()
                .any(|l| l["op"] == "added" && l["text"] == "name = \"cfg_saw\""),
            "{checked:#}"
        );

        // A change says which version it was made on, and comes from no
        // other site's page.
        put(&admin, &renamed, None, None)
            .await
            .expect_problem(428, "if-match-required");
        put(&admin, &renamed, Some(&etag), Some("http://evil.example"))
            .await
            .expect_problem(403, "foreign-origin");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), original);

        // Applied: written whole, the old version kept with its mode,
        // reloaded, and answered in words.
        let own = format!("http://127.0.0.1:{}", d.http.port());
        let applied = put(&admin, &renamed, Some(&etag), Some(&own)).await;
        let new_etag = header(&applied, "etag");
        let applied = applied.expect(200);
        assert_eq!(
            new_etag,
            format!("\"{}\"", applied["sha256"].as_str().unwrap())
        );
        let said = applied["reload"]["changes"].to_string();
        assert!(said.contains("cfg_saw"), "{applied:#}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), renamed);
        assert_eq!(mode(&path), 0o640);
        let kept = dir.path().join("drivegate.toml.1");
        assert_eq!(std::fs::read_to_string(&kept).unwrap(), original);
        assert_eq!(mode(&kept), 0o640);
        let names: Vec<String> = d.plant.now().drives().map(|d| d.name.clone()).collect();
        assert!(
            names.contains(&"cfg_saw".to_string()) && !names.contains(&"cfg_press".to_string()),
            "{names:?}"
        );
        let (file, _) = read(&admin).await;
        assert_eq!(file["last_change"]["by"], "http cfgadmin", "{file:#}");
        assert_eq!(file["generations"].as_array().unwrap().len(), 1);
        // Only the temporary's name is never left behind.
        assert!(!dir.path().join(".drivegate.toml.new").exists());

        // The second admin, on the version read before: refused, the
        // first one's change named.
        let stale = original.replace("name = \"cfg_belt\"", "name = \"cfg_conveyor\"");
        let refused = put(&second, &stale, Some(&etag), None)
            .await
            .expect_problem(412, "config-edited");
        let detail = refused["detail"].as_str().unwrap();
        assert!(
            detail.contains("http cfgadmin")
                && detail.contains("name = \"cfg_press\" became name = \"cfg_saw\""),
            "{detail}"
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), renamed);

        // Changed by hand: said so.
        let by_hand = format!("{renamed}# a note typed with sudoedit\n");
        std::fs::write(&path, &by_hand).unwrap();
        let refused = put(&admin, &renamed, Some(&new_etag), None)
            .await
            .expect_problem(412, "config-edited");
        assert!(
            refused["detail"]
                .as_str()
                .unwrap()
                .contains("changed on disk, not through drivegate"),
            "{refused:#}"
        );

        // The audit log has who and the lines.
        let log = log_text();
        let audited = log.lines().any(|l| {
            l.contains("configuration file changed")
                && l.contains("http cfgadmin")
                && l.contains("+name = \\\"cfg_saw\\\"")
        });
        assert!(audited, "no audit line with the change's lines");

        // A token made, used, listed with its last use, and revoked.
        let made = admin
            .post(
                "/api/v1/tokens",
                json!({"name": "cfg_scada", "role": "operator"}),
            )
            .await
            .expect(200);
        let secret = made["token"].as_str().unwrap().to_string();
        assert_eq!((secret.len(), &made["first"]), (64, &json!(false)));
        assert!(
            made["reload"]["changes"].to_string().contains("token"),
            "{made:#}"
        );
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("name = \"cfg_scada\"") && !text.contains(&secret));
        assert!(text.contains("# a note typed with sudoedit"), "{text}");
        let scada = admin.with_token(Some(&secret));
        let me = scada.get("/api/v1/whoami").await.expect(200);
        assert_eq!(
            (&me["who"], &me["role"]),
            (&json!("cfg_scada"), &json!("operator"))
        );
        let tokens = admin.get("/api/v1/tokens").await.expect(200);
        let listed = |name: &str| {
            tokens["tokens"]
                .as_array()
                .unwrap()
                .iter()
                .find(|t| t["name"] == name)
                .cloned()
                .unwrap_or(Value::Null)
        };
        let scada_row = listed("cfg_scada");
        assert_eq!(scada_row["role"], "operator");
        assert!(scada_row["last_used"].is_string(), "{tokens:#}");
        assert!(
            scada_row["defined"]
                .as_str()
                .unwrap()
                .starts_with("drivegate.toml:"),
            "{scada_row}"
        );
        assert!(listed("cfgsecond")["last_used"].is_string());
        admin
            .post(
                "/api/v1/tokens",
                json!({"name": "cfg_scada", "role": "viewer"}),
            )
            .await
            .expect_problem(400, "invalid-request");
        let revoked = admin.delete("/api/v1/tokens/cfg_scada").await.expect(200);
        assert_eq!(revoked["name"], "cfg_scada");
        scada
            .get("/api/v1/whoami")
            .await
            .expect_problem(401, "unauthorized");
        admin
            .delete("/api/v1/tokens/cfg_scada")
            .await
            .expect_problem(404, "unknown-token");
        let log = log_text();
        assert!(
            log.contains("API token \\\"cfg_scada\\\" made (operator)"),
            "the token's making is not audited"
        );
        assert!(
            log.contains("API token \\\"cfg_scada\\\" revoked"),
            "the token's revocation is not audited"
        );
        d.stop().await;
    })
    .await;
}

/// Makes `dir` immutable (no file created, renamed or removed in it, by
/// root too), and undoes it when dropped; `None` where the file system or
/// the test's privileges do not allow it.
struct Immutable<'a>(&'a Path);

impl<'a> Immutable<'a> {
    fn set(dir: &'a Path) -> Option<Self> {
        let ok = std::process::Command::new("chattr")
            .arg("+i")
            .arg(dir)
            .status()
            .is_ok_and(|s| s.success());
        ok.then_some(Immutable(dir))
    }
}

impl Drop for Immutable<'_> {
    fn drop(&mut self) {
        let _ = std::process::Command::new("chattr")
            .arg("-i")
            .arg(self.0)
            .status();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_file_drivegate_may_not_write_stays_and_the_change_is_offered() {
    bounded(LIMIT, async {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        let original = plant();
        let d = TestDaemon::reloadable_at(&path, &original).await;
        let admin = Api::new(d.http, Some(ADMIN));
        let (_, etag) = read(&admin).await;
        // Tests run as root, for whom permissions do not keep a file
        // read-only; an immutable directory does (as a read-only /etc).
        let Some(_immutable) = Immutable::set(dir.path()) else {
            println!(
                "skipped: chattr +i is not allowed here (needs CAP_LINUX_IMMUTABLE and ext4/xfs)"
            );
            d.stop().await;
            return;
        };
        let (file, _) = read(&admin).await;
        assert_eq!(file["writable"], false, "{file:#}");
        let why = file["not_writable"].as_str().unwrap();
        assert!(
            why.contains("drivegate may not write") && why.contains("sudoedit"),
            "{why}"
        );
        let renamed = original.replace("name = \"cfg_press\"", "name = \"cfg_saw\"");
        let refused = put(&admin, &renamed, Some(&etag), None)
            .await
            .expect_problem(409, "config-read-only");
        assert!(
            refused["detail"]
                .as_str()
                .unwrap()
                .contains("nothing was written"),
            "{refused:#}"
        );
        // A token is made, and its file offered: nothing is written.
        let made = admin
            .post(
                "/api/v1/tokens",
                json!({"name": "cfg_ro", "role": "viewer"}),
            )
            .await
            .expect(200);
        assert_eq!(made["reload"], Value::Null);
        assert!(
            made["not_written"]
                .as_str()
                .unwrap()
                .contains("may not write"),
            "{made:#}"
        );
        assert!(
            made["file_text"]
                .as_str()
                .unwrap()
                .contains("name = \"cfg_ro\"")
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), original);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        d.stop().await;
    })
    .await;
}
