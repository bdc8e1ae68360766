//! Parameters set over CAN during a run (`set` actions): each write answered at the next
//! step, every accepted change a `/rosout` line, and the log replayed bit for bit with a
//! hundred random writes in it, refusals included.

mod common;

use drivelog::msg::{Log, decode};
use firmware::control::{RESTORE, STORE, SaveOutcome};
use firmware::params::{Change, PARAMS, ParamType, service_node};
use firmware::protocol::canopen::{self, Message, SdoResponse};
use firmware::protocol::robot::Telemetry;
use hostsim::bus::SplitMix64;
use hostsim::replay::{read_log, replay_mcap};
use hostsim::scenario::{
    Action, FaultName, NodeFault, ParamName, ParamSet, Scenario, StoreCommand,
};

/// The square with `n` writes of random parameters at random times after the enable: values
/// drawn across and beyond each one's range, so that some are refused (out of range, the
/// wrong state, read-only, or a rule of the configuration) and some are taken.
fn square_with_writes(n: usize, seed: u64) -> Scenario {
    let mut s = Scenario::builtin("square").unwrap();
    let mut rng = SplitMix64(seed);
    let writable: Vec<_> = PARAMS.iter().collect();
    for _ in 0..n {
        let p = writable[(rng.next_u64() % writable.len() as u64) as usize];
        let at_s = 0.5 + rng.unit() * (s.duration_s - 1.0);
        let high = if p.high.is_finite() { p.high } else { 100.0 };
        let span = high - p.low;
        let mut value = p.low - 0.1 * span + rng.unit() * 1.2 * span;
        if p.ty != ParamType::Real32 {
            value = value.round().max(0.0);
        }
        // Mostly near the configuration's own value, so that many writes are taken.
        if rng.unit() < 0.6
            && let Ok(raw) = p.read(&s.config)
        {
            let now = p.ty.to_f64(raw);
            value = if p.ty == ParamType::Real32 {
                now * (0.8 + 0.4 * rng.unit())
            } else {
                now
            };
        }
        let mut a = Action::at(at_s);
        a.set = Some(ParamSet {
            param: ParamName(p),
            value,
        });
        s.actions.push(a);
    }
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    // As a client writes: the next request after the answer to the last (2 ms apart at least;
    // the service keeps one request a step, and a newer one replaces it).
    let mut last = f64::NEG_INFINITY;
    for a in s.actions.iter_mut().filter(|a| a.set.is_some()) {
        a.at_s = a.at_s.max(last + 0.002);
        last = a.at_s;
    }
    s
}

#[test]
fn a_hundred_random_writes_are_answered_logged_and_replay_bit_identically() {
    let s = square_with_writes(100, 47);
    let path = common::scratch("params", "writes.mcap");
    common::logged_run(&s, &path);
    let node = service_node(&s.config);

    // Every write answered once, at the step after it arrived.
    let content = read_log(&path).unwrap();
    let answers: Vec<SdoResponse> = content
        .tx
        .iter()
        .filter_map(|f| match canopen::decode(&f.frame) {
            Ok(Message::SdoResponse { node: n, response }) if n.get() == node => Some(response),
            _ => None,
        })
        .collect();
    assert_eq!(answers.len(), 100);
    let taken = answers
        .iter()
        .filter(|r| matches!(r, SdoResponse::Downloaded { .. }))
        .count();
    let refused = 100 - taken;
    assert!(
        taken >= 20 && refused >= 20,
        "{taken} taken, {refused} refused"
    );
    // Fixed parameters are always refused: read-only.
    for (a, r) in s.actions.iter().filter_map(|a| a.set).zip(&answers) {
        if a.param.0.change == Change::Fixed {
            assert!(
                matches!(
                    r,
                    SdoResponse::Abort {
                        code: 0x0601_0002,
                        ..
                    }
                ),
                "{}: {r:?}",
                a.param.0.name
            );
        }
    }

    // A /rosout line per value changed, naming both config ids.
    let bytes = std::fs::read(&path).unwrap();
    let mut lines = Vec::new();
    drivelog::for_each_message(
        &bytes,
        |m| {
            if m.topic == "/rosout" {
                let l: Log = decode(m.data).unwrap();
                if l.msg.contains(", config 0x") {
                    lines.push(l.msg);
                }
            }
        },
        |_, _| {},
    )
    .unwrap();
    assert!(
        !lines.is_empty() && lines.len() <= taken,
        "{} lines, {taken} taken",
        lines.len()
    );
    assert!(lines.iter().all(|l| l.contains(" -> ")), "{lines:?}");

    // The log replays bit for bit: the writes are inbound frames, served at the same steps.
    let report = replay_mcap(&path).unwrap();
    assert!(report.identical(), "{:?}", report.difference);
}

#[test]
fn a_set_action_names_a_parameter_and_a_value_its_type_holds() {
    let base = "duration_s = 2.0\n[[actions]]\nat_s = 0.1\n";
    let ok = Scenario::from_toml(
        &format!("{base}set = {{ param = \"gains.kp\", value = 1.5 }}\n"),
        std::path::Path::new("set.toml"),
    );
    assert_eq!(ok.unwrap().actions[0].set.unwrap().param.0.name, "gains.kp");
    let unknown = Scenario::from_toml(
        &format!("{base}set = {{ param = \"gains.kq\", value = 1 }}\n"),
        std::path::Path::new("set.toml"),
    );
    let e = unknown.unwrap_err().to_string();
    assert!(e.contains("no parameter \"gains.kq\""), "{e}");
    let fraction = Scenario::from_toml(
        &format!("{base}set = {{ param = \"timing.command_timeout_ms\", value = 1.5 }}\n"),
        std::path::Path::new("set.toml"),
    );
    let e = fraction.unwrap_err().to_string();
    assert!(
        e.contains("actions[0].set.value") && e.contains("1.5"),
        "{e}"
    );
}

/// The service's responses to saves and restores in a log, with their step times (ns).
fn store_answers(content: &hostsim::replay::LogContent, node: u8) -> Vec<(u64, SdoResponse)> {
    content
        .tx
        .iter()
        .filter_map(|f| match canopen::decode(&f.frame) {
            Ok(Message::SdoResponse { node: n, response }) if n.get() == node => {
                let (index, _) = response.object();
                matches!(index, STORE | RESTORE).then_some((f.t_ns, response))
            }
            _ => None,
        })
        .collect()
}

fn store_at(at_s: f64, command: StoreCommand) -> Action {
    let mut a = Action::at(at_s);
    a.store = Some(command);
    a
}

#[test]
fn saves_are_answered_once_stored_logged_and_replay_bit_identically() {
    // Random writes, and saves among them: one while enabled (taken: nothing is erased), a
    // restore while enabled (refused), a restore once disabled.
    let mut s = square_with_writes(40, 5);
    let end = s.duration_s;
    for (at_s, command) in [
        (1.0, StoreCommand::Save),
        (2.0, StoreCommand::Restore),
        (4.0, StoreCommand::Save),
        (end - 0.4, StoreCommand::Save),
    ] {
        s.actions.push(store_at(at_s, command));
    }
    let mut off = Action::at(end - 0.3);
    off.disable = true;
    s.actions.push(off);
    s.actions.push(store_at(end - 0.2, StoreCommand::Restore));
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    let path = common::scratch("params", "saves.mcap");
    common::logged_run(&s, &path);
    let content = read_log(&path).unwrap();
    let answers = store_answers(&content, service_node(&s.config));
    let stores: Vec<&Action> = s.actions.iter().filter(|a| a.store.is_some()).collect();
    assert_eq!(answers.len(), stores.len(), "{answers:?}");
    for (a, (t_ns, r)) in stores.iter().zip(&answers) {
        #[allow(clippy::cast_precision_loss)]
        let waited_ms = (*t_ns as f64 * 1e-6) - a.at_s * 1e3;
        match (a.store, a.at_s) {
            (Some(StoreCommand::Restore), 2.0) => {
                assert!(
                    matches!(
                        r,
                        SdoResponse::Abort {
                            code: 0x0800_0022,
                            ..
                        }
                    ),
                    "{r:?}"
                );
            }
            _ => {
                assert!(matches!(r, SdoResponse::Downloaded { .. }), "{a:?}: {r:?}");
                // Acknowledged within 30 ms of the request (25 steps at 1 kHz).
                assert!(waited_ms <= 30.0, "{a:?}: answered after {waited_ms} ms");
            }
        }
    }
    // Each end of a save is an input on /firmware/store.
    assert_eq!(content.saves.len(), 4);
    assert!(
        content
            .saves
            .iter()
            .all(|s| matches!(s.outcome, SaveOutcome::Stored { .. }))
    );
    let report = replay_mcap(&path).unwrap();
    assert!(report.identical(), "{:?}", report.difference);
}

#[test]
fn a_restarted_core_runs_the_set_it_saved() {
    let mut s = Scenario::builtin("square").unwrap();
    let kp = firmware::params::find("gains.kp").unwrap();
    let mut set = Action::at(1.0);
    set.set = Some(ParamSet {
        param: ParamName(kp),
        value: 1.25,
    });
    s.actions.push(set);
    s.actions.push(store_at(1.1, StoreCommand::Save));
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    s.node_faults.push(NodeFault {
        kind: FaultName::RunnerRestart,
        from_us: 3_000_000,
        until_us: 3_200_000,
    });
    let path = common::scratch("params", "restart.mcap");
    common::logged_run(&s, &path);
    let content = read_log(&path).unwrap();
    let mut saved = s.config;
    saved.gains.kp = 1.25;
    let heartbeat_ids: Vec<(u64, u16)> = content
        .tx
        .iter()
        .filter_map(|f| match Telemetry::decode(&f.frame) {
            Ok(Telemetry::Heartbeat(h)) => Some((f.t_ns, h.config_id)),
            _ => None,
        })
        .collect();
    let before = heartbeat_ids.iter().filter(|(t, _)| *t < 1_000_000_000);
    assert!(before.clone().count() > 5 && before.clone().all(|&(_, id)| id == s.config.id()));
    let after: Vec<_> = heartbeat_ids
        .iter()
        .filter(|(t, _)| *t > 3_200_000_000)
        .collect();
    assert!(
        after.len() > 5,
        "{} heartbeats after the restart",
        after.len()
    );
    assert!(after.iter().all(|&&(_, id)| id == saved.id()), "{after:?}");
}
