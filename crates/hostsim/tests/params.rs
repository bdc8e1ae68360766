//! Parameters set over CAN during a run (`set` actions): each write answered at the next
//! step, every accepted change a `/rosout` line, and the log replayed bit for bit with a
//! hundred random writes in it, refusals included.

mod common;

use drivelog::msg::{Log, decode};
use firmware::params::{Change, PARAMS, ParamType, service_node};
use firmware::protocol::canopen::{self, Message, SdoResponse};
use hostsim::bus::SplitMix64;
use hostsim::replay::{read_log, replay_mcap};
use hostsim::scenario::{Action, ParamName, ParamSet, Scenario};

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
