//! `kill -9` of the daemon: the broker delivers the NDEATH registered as
//! its will, with the bdSeq of the NBIRTH it ends; the next process goes
//! on with the next bdSeq (kept in the state directory).

use std::process::Stdio;
use std::time::Duration;

use drivegate::mqtt::metric::Value;

use super::config;
use crate::support::bounded;
use crate::support::mosquitto::Mosquitto;
use crate::support::sparkplug::Host;

const WAIT: Duration = Duration::from_secs(20);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_delivers_the_ndeath() {
    bounded(Duration::from_secs(60), async {
        let broker = Mosquitto::start();
        let mut host = Host::connect(broker.port, "death-host", None).await;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        let toml = format!(
            "{}[safety]\nstate_dir = \"{}\"\n",
            config(&broker.url(), ""),
            dir.path().join("state").display()
        );
        std::fs::write(&path, toml).unwrap();
        let serve = || {
            tokio::process::Command::new(env!("CARGO_BIN_EXE_drivegate"))
                .arg("serve")
                .arg("--config")
                .arg(&path)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .kill_on_drop(true)
                .spawn()
                .unwrap()
        };
        let mut child = serve();
        let nbirth = host.next(WAIT, "NBIRTH", |m| m.is("NBIRTH", None)).await;
        let bd_seq = nbirth.value("bdSeq").expect("bdSeq");
        let Value::Int(first) = bd_seq else {
            panic!("bdSeq is {bd_seq:?}")
        };
        child.start_kill().unwrap(); // SIGKILL
        child.wait().await.unwrap();
        let ndeath = host.next(WAIT, "NDEATH", |m| m.is("NDEATH", None)).await;
        assert_eq!(
            ndeath.value("bdSeq"),
            Some(bd_seq),
            "the NDEATH ends that NBIRTH"
        );
    })
    .await;
}
