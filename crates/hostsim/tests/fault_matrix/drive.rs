//! The drive every fault is injected into, the moments of it a fault starts at, and the
//! scenario edits that inject one.

use std::path::Path;

use hostsim::bus::{self, FaultKind, Node};
use hostsim::scenario::{Action, Scenario};

/// Enable at 50 ms; 0.6 m/s forward from 0.1 s (accelerating at 4 m/s² until 0.25 s, then
/// cruising); from 0.6 s `turn` (the ramp into it takes about 0.1 s). Twists stream at
/// 50 Hz.
pub(super) fn drive(turn: [f32; 3], duration_s: f64) -> Scenario {
    let mut s = Scenario::from_toml("duration_s = 1.0\nseed = 11", Path::new("matrix.toml"))
        .expect("a minimal scenario");
    s.duration_s = duration_s;
    s.actions = vec![
        Action {
            enable: true,
            ..Action::at(0.05)
        },
        Action::twist(0.1, 0.6, 0.0, 0.0),
        Action::twist(0.6, turn[0], turn[1], turn[2]),
    ];
    s
}

pub(super) const TURN: [f32; 3] = [0.4, 0.2, 1.0];

/// The moments of the drive a fault starts at.
pub(super) const MOMENTS: [(f64, &str); 3] = [
    (0.15, "accelerating"),
    (0.40, "cruising"),
    (0.75, "turning"),
];

/// How long each run goes on after the onset, s.
pub(super) const TAIL_S: f64 = 0.35;

pub(super) fn at(onset_s: f64) -> Scenario {
    drive(TURN, onset_s + TAIL_S)
}

pub(super) fn us(s: f64) -> u64 {
    (s * 1e6).round() as u64
}

pub(super) fn bus_fault(s: &mut Scenario, kind: FaultKind, from_s: f64, len_s: f64, sender: Node) {
    s.bus_faults.push(bus::Fault {
        kind,
        from_us: us(from_s),
        until_us: us(from_s + len_s),
        sender: Some(sender),
    });
}

pub(super) fn add_action(s: &mut Scenario, a: Action) {
    s.actions.push(a);
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
}

/// The drive with a bus fault of `kind` on the frames from `sender`, for `len_s` from the
/// onset `onset_s` on.
pub(super) fn faulted(onset_s: f64, kind: FaultKind, len_s: f64, sender: Node) -> Scenario {
    let mut s = at(onset_s);
    bus_fault(&mut s, kind, onset_s, len_s, sender);
    s
}

/// `s` with the host silent from `at_s` on.
pub(super) fn silenced(mut s: Scenario, at_s: f64) -> Scenario {
    add_action(
        &mut s,
        Action {
            silence: true,
            ..Action::at(at_s)
        },
    );
    s
}
