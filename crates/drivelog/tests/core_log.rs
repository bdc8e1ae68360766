//! What a run logs of its core, at each step: status lines at every change, the snapshot and
//! the odometry at their cadence, the ground truth beside the odometry, all of it at the end.

use std::collections::BTreeMap;

use drivelog::{CoreLog, McapLog, for_each_message, msg};
use firmware::control::{Controller, Instant};
use firmware::protocol::robot::{Command, ModeRequest};
use firmware::{CanFrame, Config};

/// Topic → (log time, text for `/rosout`) of a log written by `write`.
fn logged(test: &str, write: impl FnOnce(&mut McapLog)) -> BTreeMap<String, Vec<(u64, String)>> {
    let path =
        std::env::temp_dir().join(format!("drivelog-core-{}-{test}.mcap", std::process::id()));
    let mut log = McapLog::create(&path, &BTreeMap::new()).unwrap();
    write(&mut log);
    log.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    let mut topics: BTreeMap<String, Vec<(u64, String)>> = BTreeMap::new();
    for_each_message(
        &bytes,
        |m| {
            let text = if m.topic == "/rosout" {
                msg::decode::<msg::Log>(m.data).unwrap().msg
            } else {
                String::new()
            };
            topics
                .entry(m.topic.to_string())
                .or_default()
                .push((m.log_time, text));
        },
        |_, _| {},
    )
    .unwrap();
    topics
}

#[test]
fn status_at_every_change_snapshot_and_odometry_at_their_cadence_truth_beside() {
    let mut ctl = Controller::new(&Config::dji_m3508_example()).unwrap();
    let enable: CanFrame = Command::Mode(ModeRequest::Enable).to_can_frame();
    let topics = logged("cadence", |log| {
        let mut core = CoreLog::new(10, 5).from_boot();
        let truth = || ([1.0, 2.0, 0.5], [0.0; 3]);
        for step in 0..30u64 {
            let t_us = step * 1000;
            if step == 12 {
                ctl.on_frame(Instant::from_micros(t_us), &enable);
            }
            ctl.step(Instant::from_micros(t_us));
            let changes = core
                .step(Some(&mut *log), t_us * 1000, &ctl, Some(&truth))
                .unwrap();
            // Enabled at step 12 (no motor has answered: the boot timeout has not run out).
            assert_eq!(changes.state, step == 12, "step {step}");
        }
        ctl.shutdown();
        core.last(Some(log), 30_000_000, &ctl, None).unwrap();
    });
    let times = |topic: &str| {
        topics[topic]
            .iter()
            .map(|(t, _)| t / 1_000_000)
            .collect::<Vec<_>>()
    };
    // Snapshots (/joint_states, /diagnostics) every 10 steps and at the end.
    assert_eq!(times("/joint_states"), [0, 10, 20, 30]);
    assert_eq!(times("/diagnostics"), [0, 10, 20, 30]);
    // Odometry every 5 steps and at the end; the truth beside it while there is one.
    assert_eq!(times("/odom"), [0, 5, 10, 15, 20, 25, 30]);
    assert_eq!(times("/ground_truth/odom"), [0, 5, 10, 15, 20, 25]);
    // From boot: DISABLED is not said; the enable and the shutdown's disable are.
    let lines: Vec<&str> = topics["/rosout"].iter().map(|(_, t)| t.as_str()).collect();
    assert_eq!(
        lines,
        ["state ENABLED, fault NONE", "state DISABLED, fault NONE"]
    );
}
