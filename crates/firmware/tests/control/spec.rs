//! `docs/control.md` against the code: its table of constants gives the values the core
//! uses, so the page a reader trusts cannot drift from them.

use firmware::control::*;

#[test]
fn the_specifications_constants_are_the_codes() {
    let page = include_str!("../../../../docs/control.md");
    let table: Vec<(&str, f64)> = page
        .lines()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let name = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            let value = cells.get(2)?.replace('_', "").parse().ok()?;
            name.chars()
                .all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_')
                .then_some((name, value))
        })
        .collect();
    let code: &[(&str, f64)] = &[
        ("RUNAWAY_SATURATION", f64::from(RUNAWAY_SATURATION)),
        ("RUNAWAY_WINDOW_US", RUNAWAY_WINDOW_US as f64),
        ("RUNAWAY_MIN_SPEED", f64::from(RUNAWAY_MIN_SPEED)),
        ("RUNAWAY_GROWTH", f64::from(RUNAWAY_GROWTH)),
        ("FIGHT_CURRENT_FRACTION", f64::from(FIGHT_CURRENT_FRACTION)),
        ("FIGHT_COMBINED_MIN", f64::from(FIGHT_COMBINED_MIN)),
        ("FIGHT_WINDOW_US", FIGHT_WINDOW_US as f64),
        (
            "ENCODER_STUCK_BAND_COUNTS",
            f64::from(ENCODER_STUCK_BAND_COUNTS),
        ),
        (
            "ENCODER_STUCK_MIN_ROTOR_RPM",
            f64::from(ENCODER_STUCK_MIN_ROTOR_RPM),
        ),
        (
            "ENCODER_STUCK_SPINNING_US",
            ENCODER_STUCK_SPINNING_US as f64,
        ),
        ("ENCODER_STUCK_DRAGGED_US", ENCODER_STUCK_DRAGGED_US as f64),
        (
            "ENCODER_STUCK_MIN_CURRENT",
            f64::from(ENCODER_STUCK_MIN_CURRENT),
        ),
        ("STANDSTILL_WHEEL_SPEED", f64::from(STANDSTILL_WHEEL_SPEED)),
        ("GYRO_BIAS_MAX_SAMPLES", f64::from(GYRO_BIAS_MAX_SAMPLES)),
        ("ODRIVE_MAX_JUMP_FACTOR", f64::from(ODRIVE_MAX_JUMP_FACTOR)),
        ("ODRIVE_STATE_GRACE_US", ODRIVE_STATE_GRACE_US as f64),
        ("ODRIVE_CLEAR_GRACE_US", ODRIVE_CLEAR_GRACE_US as f64),
        (
            "WHEEL_TEST_CURRENT_FRACTION",
            f64::from(WHEEL_TEST_CURRENT_FRACTION),
        ),
        ("CANOPEN_SDO_TIMEOUT_US", CANOPEN_SDO_TIMEOUT_US as f64),
        (
            "CIA402_TRANSITION_TIMEOUT_US",
            CIA402_TRANSITION_TIMEOUT_US as f64,
        ),
        ("CIA402_RESET_GRACE_US", CIA402_RESET_GRACE_US as f64),
        ("CANOPEN_NMT_GRACE_US", CANOPEN_NMT_GRACE_US as f64),
        ("SLIP_TIME_CONSTANT_S", f64::from(SLIP_TIME_CONSTANT_S)),
    ];
    assert_eq!(
        table.iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        code.iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        "docs/control.md lists the constants the code exports, in this order"
    );
    for ((name, doc), (_, value)) in table.iter().zip(code) {
        // The page gives the f32 constants as written in the source: equal at f32 precision.
        assert!(
            (doc - value).abs() <= 1e-6 * value.abs(),
            "docs/control.md: {name} = {doc}, the code says {value}"
        );
    }
}
