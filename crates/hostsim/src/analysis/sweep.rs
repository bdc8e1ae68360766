//! Many runs at once: a family of lockstep runs of one scenario over seeds and parameter
//! values, on every core (`hostsim sweep`).
//!
//! A sweep is the product of its seeds and its parameter grids (`--set gains.kp=0.8,1.0,1.2`);
//! a parameter given as a range (`--set plant.mass_kg=18..24`) is drawn at random, uniformly,
//! for each run from a generator seeded by the run's index, so the same sweep draws the same
//! values. Runs are independent (each builds its own firmware core, plant and bus), run on a
//! rayon pool and are collected in their index order: the table is the same on any number of
//! threads, and each row is what `hostsim run` with the row's seed and values gives
//! ([`Row::reproduce`]).
//!
//! Parameter names: `plant.<field>` sets the simulated robot ([`PlantSpec`](crate::nodes::plant::PlantSpec): `wheel_radius`,
//! `lx`, `ly`, `roller_drag`, `mass_kg`); any other dotted name is a field of the drive
//! configuration as its TOML file names it (`gains.kp`, `limits.max_current`,
//! `timing.command_timeout_ms`, ...). Every name and value is checked before any run starts,
//! with the configuration's own validation.

use rayon::prelude::*;

use crate::bus::SplitMix64;
use crate::engine::{LogOptions, run_observed};
use crate::scenario::{Scenario, SetError};

/// Why a sweep cannot be set up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SweepError {
    /// A `--set` or `--seeds` argument that does not parse.
    #[error("{arg}: {why}")]
    Syntax {
        /// The argument as given.
        arg: String,
        /// What is wrong with it.
        why: String,
    },
    /// A value that cannot be set.
    #[error(transparent)]
    Set(#[from] SetError),
}

/// The values of one swept parameter.
#[derive(Debug, Clone, PartialEq)]
pub enum Values {
    /// Every one of these (a grid axis).
    List(Vec<f64>),
    /// A uniform random draw in `[lo, hi]` for each run.
    Range(f64, f64),
}

/// One `--set KEY=VALUES`.
#[derive(Debug, Clone, PartialEq)]
pub struct Param {
    /// The dotted name, e.g. `gains.kp` or `plant.mass_kg`.
    pub key: String,
    /// Its values.
    pub values: Values,
}

impl Param {
    /// Parses `KEY=V1,V2,...` (a grid axis; one value is a constant) or `KEY=LO..HI` (random
    /// draws).
    ///
    /// # Errors
    /// [`SweepError::Syntax`] naming the argument.
    pub fn parse(arg: &str) -> Result<Self, SweepError> {
        let syntax = |why: &str| SweepError::Syntax {
            arg: arg.to_string(),
            why: why.to_string(),
        };
        let (key, values) = arg
            .split_once('=')
            .ok_or_else(|| syntax("expected KEY=V1,V2,... or KEY=LO..HI"))?;
        let key = key.trim();
        if key.is_empty() || !key.contains('.') {
            return Err(syntax(
                "expected a dotted field name, e.g. gains.kp or plant.mass_kg",
            ));
        }
        let number = |s: &str| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| syntax(&format!("{:?} is not a finite number", s.trim())))
        };
        let values = if let Some((lo, hi)) = values.split_once("..") {
            let (lo, hi) = (number(lo)?, number(hi)?);
            if lo > hi {
                return Err(syntax("the range's low end is above its high end"));
            }
            Values::Range(lo, hi)
        } else {
            Values::List(values.split(',').map(number).collect::<Result<_, _>>()?)
        };
        Ok(Self {
            key: key.to_string(),
            values,
        })
    }
}

/// The most runs one sweep takes (seeds times the grid's combinations), and so the most
/// seeds: its plan is built in memory before the first run, and it is counted first.
pub const MAX_RUNS: u64 = 1_000_000;

/// Parses `--seeds`: `A..B` (A up to B, both included), `A..=B`, or a list `1,5,9`; at most
/// [`MAX_RUNS`] seeds, counted before the list is built.
///
/// # Errors
/// [`SweepError::Syntax`] naming the argument.
pub fn parse_seeds(arg: &str) -> Result<Vec<u64>, SweepError> {
    let syntax = |why: &str| SweepError::Syntax {
        arg: format!("--seeds {arg}"),
        why: why.to_string(),
    };
    let number = |s: &str| {
        s.trim()
            .parse::<u64>()
            .map_err(|_| syntax(&format!("{:?} is not a seed (0 or more)", s.trim())))
    };
    let too_many = |count: u128| {
        syntax(&format!(
            "{count} seeds; a sweep takes at most {MAX_RUNS} runs"
        ))
    };
    if let Some((lo, hi)) = arg.split_once("..") {
        let (lo, hi) = (number(lo)?, number(hi.trim_start_matches('='))?);
        if lo > hi {
            return Err(syntax("the range's low end is above its high end"));
        }
        let count = u128::from(hi - lo) + 1;
        if count > u128::from(MAX_RUNS) {
            return Err(too_many(count));
        }
        Ok((lo..=hi).collect())
    } else {
        let count = arg.split(',').count() as u128;
        if count > u128::from(MAX_RUNS) {
            return Err(too_many(count));
        }
        arg.split(',').map(number).collect()
    }
}

/// One run of a sweep: its index, seed and parameter values.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSpec {
    /// Position in the table.
    pub index: usize,
    /// The scenario's seed for this run.
    pub seed: u64,
    /// `(key, value)` of every parameter, in the order they were given.
    pub values: Vec<(String, f64)>,
}

/// How many runs `seeds` and `params` make: the seeds times every grid axis's length (a range
/// parameter is drawn per run and adds none), counted without building them.
///
/// # Errors
/// [`SweepError::Syntax`] naming the count and [`MAX_RUNS`] when there are more.
pub fn count_runs(seeds: usize, params: &[Param]) -> Result<u64, SweepError> {
    let count = params
        .iter()
        .map(|p| match &p.values {
            Values::List(list) => list.len() as u128,
            Values::Range(..) => 1,
        })
        .fold(seeds as u128, u128::saturating_mul);
    if count > u128::from(MAX_RUNS) {
        return Err(SweepError::Syntax {
            arg: "--seeds and --set".to_string(),
            why: format!(
                "{count} runs ({seeds} seeds times the grid's values); a sweep takes at most {MAX_RUNS}"
            ),
        });
    }
    Ok(count as u64)
}

/// The runs of a sweep: every seed with every combination of the grid axes (the first
/// parameter varying slowest, the seeds fastest), range parameters drawn per run. Counted
/// first ([`count_runs`]): a plan over [`MAX_RUNS`] is refused before it is built.
///
/// # Errors
/// [`SweepError::Syntax`] from [`count_runs`].
pub fn expand(seeds: &[u64], params: &[Param]) -> Result<Vec<RunSpec>, SweepError> {
    count_runs(seeds.len(), params)?;
    let mut combos: Vec<Vec<Option<f64>>> = vec![Vec::new()];
    for p in params {
        combos = match &p.values {
            Values::List(list) => combos
                .into_iter()
                .flat_map(|c| {
                    list.iter().map(move |&v| {
                        let mut c = c.clone();
                        c.push(Some(v));
                        c
                    })
                })
                .collect(),
            Values::Range(..) => combos
                .into_iter()
                .map(|mut c| {
                    c.push(None);
                    c
                })
                .collect(),
        };
    }
    let mut runs = Vec::with_capacity(combos.len() * seeds.len());
    for combo in &combos {
        for &seed in seeds {
            let index = runs.len();
            let mut rng = SplitMix64(0x5EED_0000_0000_0000 ^ index as u64);
            let values = params
                .iter()
                .zip(combo)
                .map(|(p, v)| {
                    let value = match (v, &p.values) {
                        (Some(v), _) => *v,
                        (None, Values::Range(lo, hi)) => lo + (hi - lo) * rng.unit(),
                        (None, Values::List(_)) => unreachable!("list values are set"),
                    };
                    (p.key.clone(), value)
                })
                .collect();
            runs.push(RunSpec {
                index,
                seed,
                values,
            });
        }
    }
    Ok(runs)
}

/// `base` with `values` applied and its seed set: the scenario of one run
/// ([`Scenario::with_values`]).
///
/// # Errors
/// [`SweepError::Set`] naming the value.
pub fn apply(base: &Scenario, seed: u64, values: &[(String, f64)]) -> Result<Scenario, SweepError> {
    Ok(base.with_values(seed, values)?)
}

/// Checks a sweep before any run: every run's names and values, and both ends of every
/// range (a draw may come near either).
///
/// # Errors
/// The first [`SweepError`] found.
pub fn check(base: &Scenario, runs: &[RunSpec], params: &[Param]) -> Result<(), SweepError> {
    for r in runs {
        apply(base, r.seed, &r.values)?;
    }
    let Some(first) = runs.first() else {
        return Ok(());
    };
    for (i, p) in params.iter().enumerate() {
        if let Values::Range(lo, hi) = p.values {
            for end in [lo, hi] {
                let mut values = first.values.clone();
                values[i].1 = end;
                apply(base, first.seed, &values)?;
            }
        }
    }
    Ok(())
}

/// One row of a sweep's table.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Row {
    /// Position in the table.
    pub index: usize,
    /// The scenario's seed.
    pub seed: u64,
    /// The parameter values, in the order given.
    pub values: Vec<(String, f64)>,
    /// The firmware's state at the end.
    pub final_state: String,
    /// The first fault (state `Fault`) or watchdog stop, `None` if none.
    pub fault: String,
    /// When it came, s (NaN: none).
    pub fault_at_s: f64,
    /// From the fault until the body stood (below 1 cm/s), s (NaN: no fault, or it never
    /// stood before the end).
    pub stop_after_fault_s: f64,
    /// Odometry against ground truth at the end, m.
    pub drift_final_m: f64,
    /// Largest odometry error over the run, m.
    pub drift_max_m: f64,
    /// The ground truth's path length, m: `drift_max_m / distance_m` is the error as a share
    /// of the distance driven (the pods' measure, docs/simulator.md, "Tracking pods").
    pub distance_m: f64,
    /// The odometry's heading less the true heading at the end, degrees.
    pub heading_error_deg: f64,
    /// RMS of the commanded minus the measured body speed (the firmware's own odometry),
    /// m/s, over the steps while enabled.
    pub tracking_rms_m_s: f64,
    /// Firmware steps run.
    pub steps: u64,
}

/// Below this body speed (m/s) the robot stands.
const STANDING_M_S: f64 = 0.01;

/// Runs one scenario and measures its row.
///
/// # Errors
/// [`SetError::Invalid`] if the configuration is refused when the run starts.
pub fn run_one(scenario: &Scenario, spec: &RunSpec) -> Result<Row, SweepError> {
    use firmware::protocol::robot::{Fault, RobotState};
    let refused = |why: String| {
        SweepError::Set(SetError::Invalid {
            key: "configuration".into(),
            value: f64::NAN,
            why,
        })
    };
    let mut plant = crate::engine::plant_for(scenario).map_err(|e| refused(e.to_string()))?;
    let period_s = 1.0 / f64::from(scenario.config.timing.control_hz);
    let mut fault: Option<(String, f64)> = None;
    let mut stood_at: Option<f64> = None;
    let mut last_pos: Option<[f64; 2]> = None;
    let (mut sq, mut n) = (0.0f64, 0u64);
    let mut distance_m = 0.0;
    let summary = run_observed(scenario, &mut plant, None, LogOptions::default(), |v| {
        let t = v.t_us as f64 * 1e-6;
        let snap = v.controller.snapshot();
        // A fault, or a watchdog stop (its reason shows while the robot is still enabled).
        if fault.is_none() && snap.fault != Fault::None {
            fault = Some((snap.fault.to_string(), t));
        }
        let pos = [v.truth[0], v.truth[1]];
        let moved = last_pos.map_or(0.0, |p| (pos[0] - p[0]).hypot(pos[1] - p[1]));
        distance_m += moved;
        let speed = moved / period_s;
        last_pos = Some(pos);
        if fault.is_some() && stood_at.is_none() && speed < STANDING_M_S {
            stood_at = Some(t);
        }
        if snap.state == RobotState::Enabled {
            let (c, m) = (snap.commanded, snap.measured);
            let e = f64::from(c.vx - m.vx).hypot(f64::from(c.vy - m.vy));
            sq += e * e;
            n += 1;
        }
    })
    .map_err(|e| refused(e.to_string()))?;
    #[allow(clippy::cast_precision_loss)]
    let tracking = if n == 0 { 0.0 } else { (sq / n as f64).sqrt() };
    Ok(Row {
        index: spec.index,
        seed: spec.seed,
        values: spec.values.clone(),
        final_state: summary.last.state.to_string(),
        fault: fault
            .as_ref()
            .map_or_else(|| "NONE".into(), |f| f.0.clone()),
        fault_at_s: fault.as_ref().map_or(f64::NAN, |f| f.1),
        stop_after_fault_s: match (&fault, stood_at) {
            (Some((_, at)), Some(stood)) => stood - at,
            _ => f64::NAN,
        },
        drift_final_m: summary.final_position_error,
        drift_max_m: summary.max_position_error,
        distance_m,
        heading_error_deg: summary.final_heading_error.to_degrees(),
        tracking_rms_m_s: tracking,
        steps: summary.steps,
    })
}

/// Runs `runs` of `base` on `threads` threads (0: one per core), calling `done` after each;
/// a run not yet started when `stop()` says so is skipped. The rows of the runs that finished,
/// in index order.
///
/// # Errors
/// The first run's error in index order (every scenario was built by [`apply`] before, so
/// only a refusal when a core starts can come here).
pub fn run_all(
    base: &Scenario,
    runs: &[RunSpec],
    threads: usize,
    stop: &(dyn Fn() -> bool + Sync),
    done: impl Fn(&Row) + Sync,
) -> Result<Vec<Row>, SweepError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| SweepError::Syntax {
            arg: format!("--jobs {threads}"),
            why: e.to_string(),
        })?;
    let rows: Vec<Option<Result<Row, SweepError>>> = pool.install(|| {
        runs.par_iter()
            .map(|spec| {
                if stop() {
                    return None;
                }
                let row = apply(base, spec.seed, &spec.values).and_then(|s| run_one(&s, spec));
                if let Ok(r) = &row {
                    done(r);
                }
                Some(row)
            })
            .collect()
    });
    rows.into_iter().flatten().collect()
}

impl Row {
    /// The command that runs this row alone: `hostsim run SCENARIO --seed S --set K=V ...`.
    #[must_use]
    pub fn reproduce(&self, scenario: &str) -> String {
        let mut cmd = format!("hostsim run {scenario} --seed {}", self.seed);
        for (k, v) in &self.values {
            cmd.push_str(&format!(" --set {k}={v}"));
        }
        cmd
    }
}

/// The table's CSV header for the parameters `keys`.
#[must_use]
pub fn csv_header(keys: &[String]) -> String {
    let mut h = vec!["index".to_string(), "seed".to_string()];
    h.extend(keys.iter().cloned());
    h.extend(
        [
            "final_state",
            "fault",
            "fault_at_s",
            "stop_after_fault_s",
            "drift_final_m",
            "drift_max_m",
            "distance_m",
            "heading_error_deg",
            "tracking_rms_m_s",
            "steps",
        ]
        .map(String::from),
    );
    h.join(",")
}

impl Row {
    /// The row as a CSV line (the columns of [`csv_header`]).
    #[must_use]
    pub fn csv(&self) -> String {
        let mut f: Vec<String> = vec![self.index.to_string(), self.seed.to_string()];
        f.extend(self.values.iter().map(|(_, v)| v.to_string()));
        f.extend([
            self.final_state.clone(),
            self.fault.clone(),
            self.fault_at_s.to_string(),
            self.stop_after_fault_s.to_string(),
            self.drift_final_m.to_string(),
            self.drift_max_m.to_string(),
            self.distance_m.to_string(),
            self.heading_error_deg.to_string(),
            self.tracking_rms_m_s.to_string(),
            self.steps.to_string(),
        ]);
        f.join(",")
    }

    /// The row as one JSON object (NaN as null).
    #[must_use]
    pub fn json(&self) -> serde_json::Value {
        let num = |x: f64| {
            if x.is_finite() {
                serde_json::json!(x)
            } else {
                serde_json::Value::Null
            }
        };
        let values: serde_json::Map<String, serde_json::Value> = self
            .values
            .iter()
            .map(|(k, v)| (k.clone(), serde_json::json!(v)))
            .collect();
        serde_json::json!({
            "index": self.index,
            "seed": self.seed,
            "values": values,
            "final_state": self.final_state,
            "fault": self.fault,
            "fault_at_s": num(self.fault_at_s),
            "stop_after_fault_s": num(self.stop_after_fault_s),
            "drift_final_m": self.drift_final_m,
            "drift_max_m": self.drift_max_m,
            "distance_m": self.distance_m,
            "heading_error_deg": self.heading_error_deg,
            "tracking_rms_m_s": self.tracking_rms_m_s,
            "steps": self.steps,
        })
    }
}

/// The `p`-th percentile (0-100) of `values` (nearest rank); NaN for none.
#[must_use]
pub fn percentile(values: &[f64], p: f64) -> f64 {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    #[allow(
        clippy::cast_possible_truncation,
        clippy::cast_sign_loss,
        clippy::cast_precision_loss
    )]
    let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
    v[rank.min(v.len()) - 1]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sets_and_seeds_parse_and_bad_ones_are_named() {
        assert_eq!(
            Param::parse("gains.kp=0.8,1.0,1.2").unwrap().values,
            Values::List(vec![0.8, 1.0, 1.2])
        );
        assert_eq!(
            Param::parse("plant.mass_kg=18..24").unwrap().values,
            Values::Range(18.0, 24.0)
        );
        assert_eq!(parse_seeds("1..3").unwrap(), [1, 2, 3]);
        assert_eq!(parse_seeds("4,2").unwrap(), [4, 2]);
        for bad in [
            "kp=1",
            "gains.kp",
            "gains.kp=a",
            "gains.kp=3..1",
            "gains.kp=inf",
        ] {
            assert!(Param::parse(bad).is_err(), "{bad}");
        }
        assert!(parse_seeds("5..2").is_err());
        // Counted before they are built: the whole u64 range, or a billion, is refused at
        // once, naming the count and the cap; the cap itself is taken.
        for (arg, count) in [
            ("0..18446744073709551615", "18446744073709551616 seeds"),
            ("1..100000000000", "100000000000 seeds"),
            ("0..1000000", "1000001 seeds"),
        ] {
            let err = parse_seeds(arg).unwrap_err().to_string();
            assert!(
                err.contains(count) && err.contains("at most 1000000 runs"),
                "{err}"
            );
        }
        assert_eq!(parse_seeds("0..999999").unwrap().len(), 1_000_000);
        let list = vec!["1"; 1_000_001].join(",");
        assert!(
            parse_seeds(&list)
                .unwrap_err()
                .to_string()
                .contains("1000001 seeds")
        );
        // Seeds times grid values: counted, capped, nothing built.
        let grid = |n: usize| Param {
            key: "gains.kp".into(),
            values: Values::List(vec![1.0; n]),
        };
        let range = Param {
            key: "gains.ki".into(),
            values: Values::Range(0.0, 1.0),
        };
        assert_eq!(count_runs(10, &[grid(3), range.clone(), grid(4)]), Ok(120));
        let err = expand(&[0; 1000], &[grid(1000), grid(2)]).unwrap_err();
        assert!(err.to_string().contains("2000000 runs"), "{err}");
        assert!(count_runs(usize::MAX, &[grid(2)]).is_err());
    }

    #[test]
    fn the_grid_is_the_product_and_draws_repeat() {
        let params = [
            Param::parse("gains.kp=1,2").unwrap(),
            Param::parse("plant.mass_kg=18..24").unwrap(),
        ];
        let runs = expand(&[7, 8, 9], &params).unwrap();
        assert_eq!(runs.len(), 6);
        assert_eq!((runs[0].seed, runs[0].values[0].1), (7, 1.0));
        assert_eq!((runs[5].seed, runs[5].values[0].1), (9, 2.0));
        assert!(runs.iter().all(|r| (18.0..=24.0).contains(&r.values[1].1)));
        assert_eq!(runs, expand(&[7, 8, 9], &params).unwrap());
    }

    #[test]
    fn names_are_checked_against_the_configuration_and_the_plant() {
        let base = Scenario::builtin("square").unwrap();
        let s = apply(
            &base,
            3,
            &[("gains.kp".into(), 0.9), ("plant.mass_kg".into(), 22.0)],
        )
        .unwrap();
        assert_eq!(
            (s.config.gains.kp, s.plant.mass_kg, s.seed),
            (0.9, Some(22.0), 3)
        );
        let e = apply(&base, 0, &[("gains.kq".into(), 1.0)])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("gains.kq: no such field; [gains] has: ") && e.contains("kp"),
            "{e}"
        );
        let e = apply(&base, 0, &[("gain.kp".into(), 1.0)])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("gain.kp: no such field; the configuration has: "),
            "{e}"
        );
        let e = apply(&base, 0, &[("plant.mass".into(), 1.0)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("plant fields: wheel_radius"), "{e}");
        let e = apply(&base, 0, &[("limits.max_current".into(), -1.0)])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("the configuration refuses limits.max_current=-1: limits.max_current = -1"),
            "{e}"
        );
        let e = apply(&base, 0, &[("timing.control_hz".into(), 1.5)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected a whole number"), "{e}");
    }

    #[test]
    fn pod_errors_and_the_gyro_bias_are_values_checked_against_the_pods_configured() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenarios/square_60s_pods.toml"
        );
        let base = Scenario::from_file(std::path::Path::new(path)).unwrap();
        let s = apply(
            &base,
            1,
            &[
                ("pods.radius_error".into(), -0.002),
                ("pods.pod[2].radius_error".into(), 0.003),
                ("pods.pod[2].offset_y".into(), 0.001),
                ("pods.misalignment_deg".into(), 0.25),
                ("pods.noise".into(), 0.0),
                ("imu.bias_deg_s".into(), -0.3),
            ],
        )
        .unwrap();
        let pods = s.pods.as_ref().unwrap();
        // The block's errors for every pod; pod 2's own added (pods 0 and 1 have none).
        assert_eq!(pods.pod.len(), 3);
        assert_eq!(pods.errors(0).radius_error, -0.002);
        assert_eq!(pods.errors(2).radius_error, -0.002 + 0.003);
        assert_eq!(
            (pods.errors(2).misalignment_deg, pods.errors(2).offset_y),
            (0.25, 0.001)
        );
        assert_eq!(s.imu.unwrap().bias_deg_s, -0.3);
        for (key, value, says) in [
            (
                "pods.pod[3].radius_error",
                0.0,
                "pods.pod[3].radius_error: no such field; the configuration has 3 pods \
                 ([[odometry.pods]]): pod[0] to pod[2]",
            ),
            (
                "pods.pod[0].radius",
                0.0,
                "pods.pod[0].radius: no such field; pods fields: noise, radius_error, \
                 misalignment_deg, and pod[I].{radius_error, misalignment_deg, offset_x, \
                 offset_y} for I in 0..3",
            ),
            (
                "pods.pod[1].radius_error",
                0.6,
                "pods.pod[1].radius_error = 0.6: expected a fraction in [-0.5, 0.5]",
            ),
            (
                "pods.radius_error",
                -0.51,
                "pods.radius_error = -0.51: expected a fraction in [-0.5, 0.5]",
            ),
            (
                "imu.bias",
                0.0,
                "imu.bias: no such field; imu fields: bias_deg_s",
            ),
        ] {
            let e = apply(&base, 0, &[(key.into(), value)])
                .unwrap_err()
                .to_string();
            assert!(e.starts_with(says), "{key}: {e}");
        }
        // The sum of the block's and a pod's own is checked too.
        let e = apply(
            &base,
            0,
            &[
                ("pods.radius_error".into(), 0.4),
                ("pods.pod[1].radius_error".into(), 0.2),
            ],
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with(
                "pods.pod[1].radius_error = 0.6000000000000001: expected with the block's"
            ),
            "{e}"
        );
        // Without a pod node (the built-in square) there is nothing to set.
        let square = Scenario::builtin("square").unwrap();
        let e = apply(&square, 0, &[("pods.noise".into(), 0.0)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("the scenario has no [pods] table"), "{e}");
    }

    #[test]
    fn percentiles_are_nearest_rank() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0, f64::NAN];
        assert_eq!(percentile(&v, 50.0), 3.0);
        assert_eq!(percentile(&v, 100.0), 5.0);
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert!(percentile(&[], 50.0).is_nan());
    }
}
