//! `hostsim sweep`: many runs of one scenario, on every core.

use std::io::{BufWriter, Write as _};
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use drivelog::Staged;
use indicatif::{ProgressBar, ProgressStyle};

use crate::engine::{LogOptions, run_metadata};
use drivelog::McapLog;

use super::*;

/// Many runs of one scenario at once, on every core: seeds and parameter values.
///
/// The runs are every seed of --seeds with every combination of the --set grids
/// (`--set gains.kp=0.8,1.0,1.2`); a --set range (`--set plant.mass_kg=18..24`) is drawn
/// at random for each run, from a generator seeded by the run's index. At most 1,000,000
/// runs (seeds times grid values), counted before any is planned. Names: a field of
/// the drive configuration as its TOML names it (gains.kp, limits.max_current,
/// timing.command_timeout_ms, ...); plant.wheel_radius, plant.lx, plant.ly,
/// plant.roller_drag, plant.mass_kg; with a [pods] table pods.noise, the pod block's
/// pods.radius_error and pods.misalignment_deg, and each pod's own
/// pods.pod[I].{radius_error,misalignment_deg,offset_x,offset_y}; with an [imu] table
/// imu.bias_deg_s, imu.noise_density. Every name and value is checked before the first
/// run. No logs (--log-worst N writes the N worst runs' logs afterwards).
///
/// Writes OUT/sweep.csv and OUT/sweep.jsonl (one row per run: index, seed, the values,
/// final state, first fault and when, time from it until the body stood, odometry drift
/// at the end and at most, the distance driven, the heading error at the end, RMS of the
/// commanded minus the measured speed, steps) and
/// OUT/sweep.png (the largest drift of each run against the first swept parameter, or
/// the seed), and prints percentiles and the worst runs, each with the command that runs
/// it alone. The table is the same on any number of threads. Ctrl-C stops starting runs
/// and writes the rows finished (exit status 130); a second Ctrl-C exits at once.
///
/// Shared out: --runs I..J (or --shard K/N) runs only those rows of the same plan, every
/// row's draws seeded by its index in the whole table, so the rows of the shards, put
/// together in index order, are the whole table's, byte for byte. Each sweep also writes
/// OUT/sweep.plan.json (the plan and its rows); --merge DIR... checks that the parts are of
/// one plan and cover its rows once, and writes the whole table and PNG into --out.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A scenario TOML file, or the name of a built-in.
    #[arg(required_unless_present = "merge")]
    pub scenario: Option<String>,
    /// Seeds: A..B (both included), or a list 1,5,9. Default: the scenario's own.
    #[arg(long, value_name = "SEEDS")]
    pub seeds: Option<String>,
    /// A parameter: KEY=V1,V2,... (a grid axis) or KEY=LO..HI (a random draw per run).
    /// Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUES")]
    pub set: Vec<String>,
    /// Drive configuration TOML (overrides the scenario's).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Threads (default: one per core).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub jobs: usize,
    /// Output folder for sweep.csv, sweep.jsonl, sweep.png and the worst runs' logs.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// How many of the worst runs (largest drift) to print.
    #[arg(long, value_name = "N", default_value_t = 5)]
    pub worst: usize,
    /// Run the N worst runs again with logs: OUT/sweep-<index>.mcap.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub log_worst: usize,
    /// Do not draw sweep.png.
    #[arg(long)]
    pub no_plot: bool,
    /// Run only rows I to J of the plan (both included, from 0): a part of the table for
    /// another machine, with the rows and draws the whole sweep gives them.
    #[arg(long, value_name = "I..J", conflicts_with = "shard")]
    pub runs: Option<String>,
    /// Run only the K-th of N equal parts of the plan (K from 1 to N): --runs for the
    /// rows of part K.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<String>,
    /// Check the sweep and run nothing: the configuration, the scenario, the seeds and every
    /// --set value (both ends of each range), and --runs or --shard against the plan; then
    /// print one JSON line: the scenario's name, the plan's runs, the rows asked and the
    /// table's CSV header. What a driver that shares the sweep out asks first
    /// (`mecanum-drive sweep --ray`).
    #[arg(long, conflicts_with_all = ["merge", "log_worst"])]
    pub check: bool,
    /// Put the parts of one sweep together: the output folders of its --runs or --shard
    /// runs, checked to be of one plan and to hold each of its rows once; writes the whole
    /// table (and PNG) into --out, byte for byte as one run writes it.
    #[arg(long, value_name = "DIR", num_args = 1.., conflicts_with_all = ["scenario", "seeds", "set", "config", "runs", "shard"])]
    pub merge: Vec<PathBuf>,
}

/// `OUT/sweep.plan.json`: which plan a table's rows are of, and which rows it holds.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PlanFile {
    /// The scenario's name (the PNG's title).
    pub scenario: String,
    /// The plan as the command gave it: the scenario argument, the configuration's id, the
    /// seeds and the --set arguments. Parts of one sweep have the same.
    pub plan: String,
    /// Runs in the whole plan.
    pub runs: u64,
    /// The rows this table holds: from, to (excluded).
    pub rows: [u64; 2],
    /// The table's CSV header.
    pub header: String,
}

/// The name of a sweep's plan file in its output folder.
pub const PLAN_FILE: &str = "sweep.plan.json";

/// The rows of a plan of `count` runs that `--runs I..J` or `--shard K/N` ask for, as a
/// half-open range (all of them without either).
///
/// # Errors
/// The argument, named with its value and what it must be, if it does not parse or is out
/// of the plan.
pub fn rows_asked(
    runs: Option<&str>,
    shard: Option<&str>,
    count: u64,
) -> Result<std::ops::Range<u64>> {
    let quoted = |s: &str| firmware::input::quote(s);
    let whole = |n: &str, arg: &str, what: &str| -> Result<u64> {
        n.trim()
            .parse::<u64>()
            .map_err(|_| anyhow::anyhow!("{arg}: {:?} is not {what}", quoted(n)))
    };
    match (runs, shard) {
        (Some(r), _) => {
            let Some((i, j)) = r.split_once("..") else {
                anyhow::bail!(
                    "--runs {:?}: expected I..J, rows I to J (from 0)",
                    quoted(r)
                );
            };
            let (i, j) = (
                whole(i, "--runs", "a row index")?,
                whole(j, "--runs", "a row index")?,
            );
            if i > j || j >= count {
                anyhow::bail!(
                    "--runs {i}..{j}: the plan has rows 0..{} ({count} runs), and I is at most J",
                    count.saturating_sub(1)
                );
            }
            Ok(i..j + 1)
        }
        (None, Some(s)) => {
            let Some((k, n)) = s.split_once('/') else {
                anyhow::bail!(
                    "--shard {:?}: expected K/N, part K of N (K from 1)",
                    quoted(s)
                );
            };
            let (k, n) = (
                whole(k, "--shard", "a part number")?,
                whole(n, "--shard", "a number of parts")?,
            );
            if n == 0 || k == 0 || k > n || n > count.max(1) {
                anyhow::bail!(
                    "--shard {k}/{n}: K is 1 to N, and N at most the plan's {count} runs"
                );
            }
            let bound = |p: u64| {
                u64::try_from(u128::from(p) * u128::from(count) / u128::from(n)).unwrap_or(count)
            };
            Ok(bound(k - 1)..bound(k))
        }
        (None, None) => Ok(0..count),
    }
}

/// A sweep before its runs are built: the base scenario, the seeds, the parameters, and how
/// many runs they make (at most [`crate::analysis::sweep::MAX_RUNS`]).
pub struct Plan {
    /// The scenario, with `--config`.
    pub base: Scenario,
    /// The seeds of `--seeds`, or the scenario's own.
    pub seeds: Vec<u64>,
    /// The `--set` parameters, in the order given.
    pub params: Vec<crate::analysis::sweep::Param>,
    /// The runs they make, counted without building them.
    pub count: u64,
}

impl Plan {
    /// The runs, built, with every name and value (and both ends of each range) checked on
    /// the base scenario: the last check before the first run. Its time and memory grow
    /// with [`Self::count`].
    ///
    /// # Errors
    /// The first value the scenario refuses.
    pub fn runs(&self) -> Result<Vec<crate::analysis::sweep::RunSpec>> {
        use crate::analysis::sweep as sw;
        let runs = sw::expand(&self.seeds, &self.params)?;
        // Every name and value (and both ends of each range), before the first run.
        sw::check(&self.base, &runs, &self.params)?;
        Ok(runs)
    }
}

/// `hostsim sweep`'s checks before its plan is built: the configuration and scenario load,
/// `--seeds` and each `--set` parse, and the runs they make are counted against the cap.
///
/// # Errors
/// The first of those that fails, naming the argument.
pub fn prepare(args: &Args) -> Result<Plan> {
    use crate::analysis::sweep::{self as sw, Param};
    let config = args
        .config
        .as_deref()
        .map(firmware::Config::from_toml_file)
        .transpose()?;
    let base = load_scenario(args.scenario.as_deref(), config)?;
    let seeds = match &args.seeds {
        Some(s) => sw::parse_seeds(s)?,
        None => vec![base.seed],
    };
    let params: Vec<Param> = args
        .set
        .iter()
        .map(|a| Param::parse(a))
        .collect::<Result<_, _>>()?;
    let count = sw::count_runs(seeds.len(), &params)?;
    Ok(Plan {
        base,
        seeds,
        params,
        count,
    })
}

/// `hostsim sweep`: many runs at once.
pub fn execute(args: &Args) -> Result<ExitCode> {
    use crate::analysis::sweep as sw;
    if !args.merge.is_empty() {
        return merge(args);
    }
    let plan = prepare(args)?;
    let asked = rows_asked(args.runs.as_deref(), args.shard.as_deref(), plan.count)?;
    let all = plan.runs()?;
    if args.check {
        let keys: Vec<String> = plan.params.iter().map(|p| p.key.clone()).collect();
        println!(
            "{}",
            serde_json::json!({
                "scenario": plan.base.name,
                "runs": plan.count,
                "rows": [asked.start, asked.end],
                "header": sw::csv_header(&keys),
            })
        );
        return Ok(ExitCode::SUCCESS);
    }
    let runs = &all[asked.start as usize..asked.end as usize];
    let Plan {
        base,
        seeds,
        params,
        count: _,
    } = plan;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    // Written as `.part` files, renamed when the sweep is whole: an interrupted or failed
    // sweep leaves the last whole table as it was (an interrupted one its rows in the `.part`).
    let staged = |path: &std::path::Path| -> Result<BufWriter<Staged>> {
        Ok(BufWriter::new(Staged::create(path)?))
    };
    let csv = staged(&args.out.join("sweep.csv"))?;
    let jsonl = staged(&args.out.join("sweep.jsonl"))?;
    let threads = if args.jobs == 0 {
        std::thread::available_parallelism().map_or(1, std::num::NonZero::get)
    } else {
        args.jobs
    };
    // Ctrl-C stops starting runs from here on: the line below says so to whoever waits on it.
    let signal = mecanum_linux::stop_on_signals()?;
    eprintln!(
        "sweep of {:?}: {} runs ({} seeds x {} values){} on {threads} threads",
        base.name,
        all.len(),
        seeds.len(),
        all.len() / seeds.len().max(1),
        if runs.len() == all.len() {
            String::new()
        } else {
            format!("; rows {}..{} here", asked.start, asked.end - 1)
        }
    );
    let wall = std::time::Instant::now();
    let rows = run_all(&base, runs, threads, &signal)?;
    let interrupted = rows.len() < runs.len();
    let keys: Vec<String> = params.iter().map(|p| p.key.clone()).collect();
    let table = write_tables(csv, jsonl, &keys, &rows, interrupted)?;
    if !interrupted {
        let plan_file = PlanFile {
            scenario: base.name.clone(),
            plan: format!(
                "{} | config 0x{:04x} | seeds {:?} | set {:?}",
                args.scenario.as_deref().unwrap_or_default(),
                base.config.id(),
                seeds,
                args.set
            ),
            runs: all.len() as u64,
            rows: [asked.start, asked.end],
            header: sw::csv_header(&keys),
        };
        drivelog::output::write_whole(
            &args.out.join(PLAN_FILE),
            (serde_json::to_string_pretty(&plan_file)? + "\n").as_bytes(),
        )?;
    }
    let secs = wall.elapsed().as_secs_f64();
    let simulated: f64 =
        rows.iter().map(|r| r.steps as f64).sum::<f64>() / f64::from(base.config.timing.control_hz);
    println!(
        "{} of {} runs in {secs:.1} s on {threads} threads ({:.0}x real time in all){}",
        rows.len(),
        runs.len(),
        simulated / secs.max(1e-9),
        if interrupted {
            "; INTERRUPTED: the rows finished are in the .part files, the last whole table \
             is as it was"
        } else {
            ""
        }
    );
    print_figures(&rows);
    let mut worst: Vec<&sw::Row> = rows.iter().collect();
    worst.sort_by(|a, b| {
        b.drift_max_m
            .total_cmp(&a.drift_max_m)
            .then(a.index.cmp(&b.index))
    });
    print_worst(args, &base, &worst)?;
    if !args.no_plot && !rows.is_empty() && !interrupted {
        let (label, xs) = plot_x(&keys, &rows);
        let ys: Vec<f64> = rows.iter().map(|r| r.drift_max_m).collect();
        plot(&args.out.join("sweep.png"), &base.name, &label, &xs, &ys)?;
    }
    println!("table: {table}");
    Ok(if interrupted {
        ExitCode::from(EXIT_INTERRUPTED)
    } else {
        ExitCode::SUCCESS
    })
}

/// Runs `runs` on `threads` threads with a progress bar; Ctrl-C stops starting runs (the
/// rows finished are returned).
fn run_all(
    base: &Scenario,
    runs: &[crate::analysis::sweep::RunSpec],
    threads: usize,
    signal: &std::sync::atomic::AtomicUsize,
) -> Result<Vec<crate::analysis::sweep::Row>> {
    let bar = ProgressBar::new(runs.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("[{bar:40}] {pos}/{len} runs, {elapsed} elapsed, ETA {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let stop = || signal.load(std::sync::atomic::Ordering::Relaxed) != 0;
    let rows = crate::analysis::sweep::run_all(base, runs, threads, &stop, |_| bar.inc(1))?;
    bar.finish_and_clear();
    Ok(rows)
}

/// Writes the rows to the staged CSV and JSON lines tables, and commits them unless the
/// sweep was `interrupted` (their `.part` files are then kept). Returns where they are.
fn write_tables(
    mut csv: BufWriter<Staged>,
    mut jsonl: BufWriter<Staged>,
    keys: &[String],
    rows: &[crate::analysis::sweep::Row],
    interrupted: bool,
) -> Result<String> {
    writeln!(csv, "{}", crate::analysis::sweep::csv_header(keys))?;
    for r in rows {
        writeln!(csv, "{}", r.csv())?;
        writeln!(jsonl, "{}", r.json())?;
    }
    let done = |w: BufWriter<Staged>| -> Result<Staged> {
        let part = w.get_ref().part().display().to_string();
        w.into_inner()
            .map_err(std::io::IntoInnerError::into_error)
            .with_context(|| format!("cannot write {part}"))
    };
    let (csv, jsonl) = (done(csv)?, done(jsonl)?);
    // Kept only for an interrupted sweep: a sweep that fails leaves no empty `.part` behind.
    if interrupted {
        let (csv, jsonl) = (csv.keep_part(), jsonl.keep_part());
        Ok(format!(
            "{} and {}",
            csv.part().display(),
            jsonl.part().display()
        ))
    } else {
        Ok(format!(
            "{} and {}",
            csv.commit()?.display(),
            jsonl.commit()?.display()
        ))
    }
}

/// The percentiles of the drift (in metres and as a share of the distance driven), the final
/// heading error, the tracking error and the stop, and the faults' counts.
fn print_figures(rows: &[crate::analysis::sweep::Row]) {
    use crate::analysis::sweep as sw;
    let column = |f: fn(&sw::Row) -> f64| rows.iter().map(f).collect::<Vec<f64>>();
    for (name, unit, values) in [
        ("drift, largest", "m", column(|r| r.drift_max_m)),
        ("drift, final", "m", column(|r| r.drift_final_m)),
        (
            "drift / distance",
            "%",
            column(|r| 100.0 * r.drift_max_m / r.distance_m),
        ),
        (
            "heading error, end",
            "°",
            column(|r| r.heading_error_deg.abs()),
        ),
        ("tracking error RMS", "m/s", column(|r| r.tracking_rms_m_s)),
        ("stop after a fault", "s", column(|r| r.stop_after_fault_s)),
    ] {
        if values.iter().all(|v| !v.is_finite()) {
            println!("{name:20} -");
            continue;
        }
        println!(
            "{name:20} p50 {:.4}  p90 {:.4}  p99 {:.4}  max {:.4} {unit}",
            sw::percentile(&values, 50.0),
            sw::percentile(&values, 90.0),
            sw::percentile(&values, 99.0),
            sw::percentile(&values, 100.0)
        );
    }
    let mut faults: std::collections::BTreeMap<&str, usize> = std::collections::BTreeMap::new();
    for r in rows {
        *faults.entry(r.fault.as_str()).or_default() += 1;
    }
    let faults: Vec<String> = faults.iter().map(|(k, n)| format!("{k} {n}")).collect();
    println!("faults: {}", faults.join(", "));
}

/// The `--worst` worst runs (`worst`, largest drift first), each with the command that runs
/// it alone; the `--log-worst` worst run again with logs.
fn print_worst(args: &Args, base: &Scenario, worst: &[&crate::analysis::sweep::Row]) -> Result<()> {
    println!("worst runs (largest drift):");
    for r in worst.iter().take(args.worst) {
        println!(
            "  #{} drift {:.4} m, fault {}: {}",
            r.index,
            r.drift_max_m,
            r.fault,
            r.reproduce(args.scenario.as_deref().unwrap_or_default())
        );
    }
    for r in worst.iter().take(args.log_worst) {
        let s = crate::analysis::sweep::apply(base, r.seed, &r.values)?;
        let path = args.out.join(format!("sweep-{}.mcap", r.index));
        let mut log = McapLog::create(&path, &run_metadata(&s))?;
        let mut plant = crate::engine::plant_for(&s)?;
        crate::engine::run(
            &s,
            &mut plant,
            Some(&mut log),
            LogOptions::default(),
            |_| {},
        )?;
        log.finish()?;
        println!("  log of #{}: {}", r.index, path.display());
    }
    Ok(())
}

/// sweep.png's x axis: the first swept parameter, or the seed.
fn plot_x(keys: &[String], rows: &[crate::analysis::sweep::Row]) -> (String, Vec<f64>) {
    match keys.first() {
        Some(k) => (k.clone(), rows.iter().map(|r| r.values[0].1).collect()),
        #[allow(clippy::cast_precision_loss)]
        None => ("seed".into(), rows.iter().map(|r| r.seed as f64).collect()),
    }
}

/// sweep.png: each run's largest drift (`ys`) against `xs`, labelled `label`.
fn plot(
    png_path: &std::path::Path,
    scenario: &str,
    label: &str,
    xs: &[f64],
    ys: &[f64],
) -> Result<()> {
    crate::analysis::plot::scatter(
        png_path,
        &format!("sweep of {scenario}"),
        label,
        "largest drift, m",
        xs,
        ys,
    )?;
    Ok(())
}

/// `--merge DIR...`: the parts of one sweep put together (see [`Args`]).
fn merge(args: &Args) -> Result<ExitCode> {
    let (plan, csv_rows, json_rows) = read_parts(&args.merge)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    let mut csv = String::with_capacity(csv_rows.iter().map(|l| l.len() + 1).sum());
    csv.push_str(&plan.header);
    csv.push('\n');
    let mut jsonl = String::new();
    for (c, j) in csv_rows.iter().zip(&json_rows) {
        csv.push_str(c);
        csv.push('\n');
        jsonl.push_str(j);
        jsonl.push('\n');
    }
    let out = |name: &str, bytes: &[u8]| drivelog::output::write_whole(&args.out.join(name), bytes);
    out("sweep.csv", csv.as_bytes())?;
    out("sweep.jsonl", jsonl.as_bytes())?;
    let merged = PlanFile {
        rows: [0, plan.runs],
        ..plan.clone()
    };
    out(
        PLAN_FILE,
        (serde_json::to_string_pretty(&merged)? + "\n").as_bytes(),
    )?;
    if !args.no_plot && plan.runs > 0 {
        // The x axis as the sweep draws it: the first swept parameter, else the seed.
        let first_key = plan
            .header
            .split(',')
            .nth(2)
            .filter(|k| *k != "final_state");
        let mut xs = Vec::with_capacity(json_rows.len());
        let mut ys = Vec::with_capacity(json_rows.len());
        for j in &json_rows {
            let v: serde_json::Value = serde_json::from_str(j).context("a JSON line of a part")?;
            let x = match first_key {
                Some(k) => v["values"][k].as_f64(),
                #[allow(clippy::cast_precision_loss)]
                None => v["seed"].as_u64().map(|s| s as f64),
            };
            xs.push(x.unwrap_or(f64::NAN));
            ys.push(v["drift_max_m"].as_f64().unwrap_or(f64::NAN));
        }
        let label = first_key.unwrap_or("seed");
        plot(&args.out.join("sweep.png"), &plan.scenario, label, &xs, &ys)?;
    }
    println!(
        "merged {} parts: {} runs of {} into {}",
        args.merge.len(),
        plan.runs,
        plan.plan,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// The parts in `dirs`, checked to be of one plan and to hold each of its rows once: the
/// plan, and every row's CSV and JSON lines in index order.
fn read_parts(dirs: &[PathBuf]) -> Result<(PlanFile, Vec<String>, Vec<String>)> {
    let mut plan: Option<PlanFile> = None;
    let mut csv_rows: Vec<Option<String>> = Vec::new();
    let mut json_rows: Vec<Option<String>> = Vec::new();
    for dir in dirs {
        let path = dir.join(PLAN_FILE);
        let text = firmware::input::read_bounded(&path, 1 << 16)
            .with_context(|| format!("--merge {}: cannot read {PLAN_FILE}", dir.display()))?;
        let part: PlanFile = serde_json::from_slice(&text)
            .with_context(|| format!("{}: not a sweep's plan file", path.display()))?;
        let whole = plan.get_or_insert_with(|| part.clone());
        if (&part.plan, part.runs, &part.header) != (&whole.plan, whole.runs, &whole.header) {
            anyhow::bail!(
                "--merge {}: a part of another sweep ({}, {} runs), not of {} ({} runs)",
                dir.display(),
                part.plan,
                part.runs,
                whole.plan,
                whole.runs
            );
        }
        let [from, to] = part.rows;
        if from > to || to > part.runs {
            anyhow::bail!(
                "{}: rows {from}..{to} of {} runs",
                path.display(),
                part.runs
            );
        }
        if csv_rows.is_empty() {
            let n = usize::try_from(part.runs).context("too many runs")?;
            csv_rows = vec![None; n];
            json_rows = vec![None; n];
        }
        let read = |name: &str| {
            std::fs::read_to_string(dir.join(name)).with_context(|| {
                format!(
                    "--merge {}: cannot read {name} (an interrupted part leaves only .part files)",
                    dir.display()
                )
            })
        };
        let (csv, jsonl) = (read("sweep.csv")?, read("sweep.jsonl")?);
        let mut lines = csv.lines();
        if lines.next() != Some(part.header.as_str()) {
            anyhow::bail!(
                "{}: its header is not the plan's",
                dir.join("sweep.csv").display()
            );
        }
        let (lines, json): (Vec<&str>, Vec<&str>) = (lines.collect(), jsonl.lines().collect());
        if lines.len() as u64 != to - from || json.len() != lines.len() {
            anyhow::bail!(
                "--merge {}: {} rows in sweep.csv and {} in sweep.jsonl where the plan file says {from}..{to}",
                dir.display(),
                lines.len(),
                json.len()
            );
        }
        for (line, json) in lines.into_iter().zip(json) {
            let index = line
                .split(',')
                .next()
                .and_then(|i| i.parse::<u64>().ok())
                .filter(|i| (from..to).contains(i))
                .with_context(|| {
                    format!(
                        "--merge {}: a row outside its rows {from}..{to}",
                        dir.display()
                    )
                })?;
            let slot = &mut csv_rows[index as usize];
            if slot.is_some() {
                anyhow::bail!("--merge {}: row {index} is in two parts", dir.display());
            }
            *slot = Some(line.to_string());
            json_rows[index as usize] = Some(json.to_string());
        }
    }
    let Some(plan) = plan else {
        anyhow::bail!("--merge: no folder given");
    };
    if let Some(missing) = csv_rows.iter().position(Option::is_none) {
        anyhow::bail!(
            "--merge: row {missing} of {} is in none of the parts",
            plan.runs
        );
    }
    Ok((
        plan,
        csv_rows.into_iter().flatten().collect(),
        json_rows.into_iter().flatten().collect(),
    ))
}
