//! The journal's file as the next process finds it: what is appended,
//! compacted, torn, garbled, lost, deleted or refused by the disk.

#![allow(clippy::unwrap_used)]
use super::format::{Action, HolderKind, ModeName};
use super::*;

fn lease(deadline_ms: u64) -> Record {
    Record::Lease {
        drive: "conveyor".into(),
        owner: "scada".into(),
        holder: HolderKind::Http,
        deadline_ms,
        length_ms: 1000,
        action: Action::ZeroSpeed,
        mode: ModeName::Speed,
    }
}

#[test]
fn what_is_appended_is_read_back_by_the_next_process() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    assert_eq!(j.health(), &Health::Ok);
    j.append(&[lease(5)]).unwrap();
    let state = j.state().clone();
    drop(j);
    let opened = Journal::open(Some(dir.path()), 4);
    assert_eq!(opened.recovered, Recovered::Read(state));
    assert!(opened.news.is_empty(), "{:?}", opened.news);
}

#[test]
fn a_growing_journal_is_compacted_to_what_it_holds() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    // 5000 records, ten to a sync.
    for i in 0..500 {
        let batch: Vec<Record> = (0..10).map(|k| lease(i * 10 + k)).collect();
        j.append(&batch).unwrap();
    }
    let c = j.counts();
    assert!(c.compactions >= 3, "{c:?}");
    assert!(c.bytes <= COMPACT_AT + 200, "{c:?}");
    let on_disk = fs::metadata(dir.path().join(FILE)).unwrap().len();
    assert_eq!(on_disk, c.bytes);
    let read = Journal::open(Some(dir.path()), 4).recovered;
    assert_eq!(read, Recovered::Read(JournalState::of(&[lease(4_999)])));
    assert!(!dir.path().join(format!("{FILE}.tmp")).exists());
}

#[test]
fn a_torn_tail_is_said_and_dropped_and_garbage_is_set_aside() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.append(&[lease(7)]).unwrap();
    drop(j);
    let path = dir.path().join(FILE);
    let mut bytes = fs::read(&path).unwrap();
    bytes.extend_from_slice(&[40, 0, 0, 0, 1, 2]);
    fs::write(&path, &bytes).unwrap();
    let opened = Journal::open(Some(dir.path()), 4);
    assert_eq!(
        opened.recovered,
        Recovered::Read(JournalState::of(&[lease(7)]))
    );
    assert!(opened.news[0].contains("cut short"), "{:?}", opened.news);
    drop(opened);
    // Rewritten without the tail.
    assert!(Journal::open(Some(dir.path()), 4).news.is_empty());

    fs::write(&path, b"garbage").unwrap();
    let opened = Journal::open(Some(dir.path()), 4);
    assert!(
        matches!(&opened.recovered, Recovered::Unknown(Unknown::Unreadable(why)) if why.contains("set aside")),
        "{:?}",
        opened.recovered
    );
    assert_eq!(opened.journal.counts().unreadable, 1);
    assert!(opened.news[0].contains("set aside"), "{:?}", opened.news);
    let aside = fs::read_dir(dir.path())
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .is_ok_and(|e| e.file_name().to_string_lossy().contains("unreadable"))
        })
        .count();
    assert_eq!(aside, 1);
}

#[test]
fn a_journal_beyond_its_bound_is_read_from_its_end() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(FILE);
    // Renewals without a clean stop, longer than the read budget.
    let mut bytes = format::header();
    let mut deadline = 0;
    while (bytes.len() as u64) < 3 * tail::CHUNK + read_budget(4) {
        deadline += 1;
        bytes.extend(format::encode(&lease(deadline)));
    }
    fs::write(&path, &bytes).unwrap();
    let opened = Journal::open(Some(dir.path()), 4);
    // The newest record read is the last word; older ones are unknown.
    assert_eq!(
        opened.recovered,
        Recovered::Tail(JournalState::of(&[lease(deadline)]))
    );
    let skipped = opened.journal.counts().skipped_bytes;
    assert!(skipped >= tail::CHUNK, "{skipped}");
    assert!(
        opened.news.iter().any(|n| n.contains("on_unknown_state")),
        "{:?}",
        opened.news
    );
    // Compacted: the next start reads it whole.
    drop(opened);
    assert!(fs::metadata(&path).unwrap().len() < 1024);
    assert!(matches!(
        Journal::open(Some(dir.path()), 4).recovered,
        Recovered::Read(_)
    ));

    // With a clean stop near its end, all that is owed is after it.
    bytes.extend(format::encode(&Record::Shutdown));
    bytes.extend(format::encode(&lease(7)));
    fs::write(&path, &bytes).unwrap();
    let opened = Journal::open(Some(dir.path()), 4);
    assert_eq!(
        opened.recovered,
        Recovered::Read(JournalState::of(&[lease(7)]))
    );
    assert!(opened.journal.counts().skipped_bytes > 0);
}

#[test]
fn a_directory_that_cannot_be_written_keeps_the_state_in_memory() {
    let dir = tempfile::tempdir().unwrap();
    let blocked = dir.path().join("a-file");
    fs::write(&blocked, b"x").unwrap();
    let mut opened = Journal::open(Some(&blocked), 4);
    assert!(matches!(
        opened.recovered,
        Recovered::Unknown(Unknown::Unreadable(_))
    ));
    assert!(matches!(opened.journal.health(), Health::Failing(_)));
    assert!(opened.journal.append(&[lease(9)]).is_err());
    assert_eq!(opened.journal.counts().write_errors, 1);
    assert_eq!(opened.journal.state(), &JournalState::of(&[lease(9)]));
    assert!(check_writable(&blocked).is_err());
    assert!(check_writable(&dir.path().join("state")).is_ok());
}

/// The journal's state after `opened`, named as the metrics name it.
fn unknown(opened: &Opened) -> Option<&'static str> {
    match &opened.recovered {
        Recovered::Unknown(u) => Some(u.name()),
        _ => None,
    }
}

#[test]
fn a_journal_that_owes_nothing_is_still_told_from_a_lost_one() {
    let dir = tempfile::tempdir().unwrap();
    // A first start: nothing there, nothing unknown, and the marker.
    let first = Journal::open(Some(dir.path()), 4);
    assert_eq!(first.recovered, Recovered::Read(JournalState::default()));
    assert!(first.news.is_empty(), "{:?}", first.news);
    assert!(dir.path().join(MARKER).exists());
    drop(first);
    // Its file owes nothing, and is more than a header: its snapshot.
    let path = dir.path().join(FILE);
    let bytes = fs::read(&path).unwrap();
    let decoded = format::decode(&bytes).unwrap();
    assert!(
        matches!(decoded.records[..], [Record::Snapshot { .. }]),
        "{decoded:?}"
    );
    assert_eq!(
        Journal::open(Some(dir.path()), 4).recovered,
        Recovered::Read(JournalState::default())
    );
    // A clean stop read back is no loss either.
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.append(&[lease(5), Record::Shutdown]).unwrap();
    drop(j);
    let opened = Journal::open(Some(dir.path()), 4);
    assert_eq!(opened.recovered, Recovered::Read(JournalState::default()));
    assert_eq!(opened.journal.counts().lost, 0);
}

#[test]
fn an_empty_or_header_only_journal_is_unknown() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.append(&[lease(5)]).unwrap();
    drop(j);
    let path = dir.path().join(FILE);
    let mut v1_header = format::header();
    v1_header[8] = 1;
    for (bytes, named) in [
        (Vec::new(), "empty"),
        (format::header()[..5].to_vec(), "empty"),
        (format::header(), "header-only"),
        (v1_header, "header-only"),
        // A header and a first record torn: still nothing whole.
        (
            [format::header(), vec![40, 0, 0, 0, 1]].concat(),
            "header-only",
        ),
    ] {
        fs::write(&path, &bytes).unwrap();
        let opened = Journal::open(Some(dir.path()), 4);
        assert_eq!(unknown(&opened), Some(named), "{bytes:?}");
        assert_eq!(opened.journal.counts().lost, 1);
        assert!(
            opened.news.iter().any(|n| n.contains("on_unknown_state")),
            "{:?}",
            opened.news
        );
        drop(opened);
        // Written whole again: the next start knows.
        assert_eq!(
            Journal::open(Some(dir.path()), 4).recovered,
            Recovered::Read(JournalState::default())
        );
    }
}

#[test]
fn a_missing_journal_is_unknown_only_where_an_earlier_run_shows() {
    // Its marker.
    let dir = tempfile::tempdir().unwrap();
    drop(Journal::open(Some(dir.path()), 4));
    fs::remove_file(dir.path().join(FILE)).unwrap();
    let opened = Journal::open(Some(dir.path()), 4);
    assert_eq!(unknown(&opened), Some("missing"));
    assert!(
        opened.news[0].contains("safety.journal.marker"),
        "{:?}",
        opened.news
    );
    // The alarm file of an earlier run, without the marker (a
    // drivegate from before the marker).
    let dir = tempfile::tempdir().unwrap();
    fs::write(dir.path().join("alarms.journal"), b"DRVGALRM").unwrap();
    assert_eq!(
        unknown(&Journal::open(Some(dir.path()), 4)),
        Some("missing")
    );
    // A journal set aside.
    let dir = tempfile::tempdir().unwrap();
    fs::write(dir.path().join(format!("{FILE}.unreadable-17")), b"x").unwrap();
    assert_eq!(
        unknown(&Journal::open(Some(dir.path()), 4)),
        Some("missing")
    );
    // A state directory of its own files (the MQTT face's bdSeq is no
    // proof the safety journal was ever written there) is a first
    // start.
    let dir = tempfile::tempdir().unwrap();
    fs::write(dir.path().join("mqtt-bdseq"), b"3").unwrap();
    assert_eq!(unknown(&Journal::open(Some(dir.path()), 4)), None);
}

#[test]
fn a_journal_deleted_while_drivegate_runs_is_written_again() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.append(&[lease(5)]).unwrap();
    fs::remove_file(dir.path().join(FILE)).unwrap();
    j.append(&[lease(6)]).unwrap();
    drop(j);
    assert_eq!(
        Journal::open(Some(dir.path()), 4).recovered,
        Recovered::Read(JournalState::of(&[lease(6)]))
    );
}

#[test]
fn a_record_the_disk_did_not_take_leaves_a_journal_that_says_it_lost_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.append(&[lease(5)]).unwrap();
    // The next append fails (a handle that cannot write stands for a
    // full disk).
    j.file = Some(File::open(dir.path().join(FILE)).unwrap());
    assert!(j.append(&[lease(6)]).is_err());
    assert!(matches!(j.health(), Health::Failing(_)));
    // A crash now: the start finds a journal that says it lost what it
    // held, not the older lease alone.
    let crashed = Journal::open(Some(dir.path()), 4);
    assert_eq!(unknown(&crashed), Some("header-only"));
    drop(crashed);
    // Without the crash, the next record writes it whole again.
    let mut j = Journal::open(Some(dir.path()), 4).journal;
    j.file = Some(File::open(dir.path().join(FILE)).unwrap());
    assert!(j.append(&[lease(7)]).is_err());
    j.append(&[lease(8)]).unwrap();
    assert_eq!(j.health(), &Health::Ok);
    drop(j);
    assert_eq!(
        Journal::open(Some(dir.path()), 4).recovered,
        Recovered::Read(JournalState::of(&[lease(8)]))
    );
}
