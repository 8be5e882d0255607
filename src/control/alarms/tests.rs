//! The alarms raised and cleared from the buses' and the core's events.

#![allow(clippy::unwrap_used)]
use super::*;

fn offline(alarms: &Alarms, drive: &str) {
    alarms.apply(|book, now| {
        book.raise(
            Raise {
                key: AlarmKey {
                    kind: AlarmKind::Offline,
                    bus: "line1".into(),
                    drive: Some(drive.into()),
                    code: 0,
                },
                text: format!("{drive} stopped answering"),
                help: help::OFFLINE.into(),
            },
            now,
        )
    });
}

#[tokio::test]
async fn an_acknowledged_alarm_is_read_back_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let events = Arc::new(Events::default());
    let mut rx = events.subscribe();
    let alarms = Alarms::open(Some(dir.path()), 10, events.clone());
    offline(&alarms, "conveyor");
    let id = alarms.list()[0].id;
    let acked = alarms.acknowledge(id, "panel").await.unwrap();
    assert_eq!(acked.ack.as_ref().unwrap().by, "panel");
    assert!(matches!(
        rx.recv().await.unwrap().event.as_ref(),
        ControlEvent::Alarm(AlarmNews::Raised(_))
    ));
    assert!(matches!(
        rx.recv().await.unwrap().event.as_ref(),
        ControlEvent::Alarm(AlarmNews::Acknowledged(_))
    ));
    alarms.close();
    let again = Alarms::open(Some(dir.path()), 10, events);
    assert_eq!(again.list(), vec![acked]);
    let s = again.summary();
    assert_eq!(s.active[&AlarmKind::Offline], 1);
    assert_eq!((s.unacknowledged, s.held), (0, 1));
    assert_eq!(s.active.len(), AlarmKind::ALL.len());
    assert!(matches!(
        again.acknowledge(99, "panel").await,
        Err(AckError::Unknown(99))
    ));
    again.close();
}
