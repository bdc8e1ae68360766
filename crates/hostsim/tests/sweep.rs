//! `hostsim sweep`: the table is the one the same runs give one by one, on any number of
//! threads; a bad name or value fails before any run; Ctrl-C keeps the rows finished.

use std::path::{Path, PathBuf};
use std::process::Command;

use hostsim::analysis::sweep::{self, Param};
use hostsim::scenario::Scenario;

fn scenario_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenarios")
        .join(name)
}

#[test]
fn the_table_is_the_runs_one_by_one_on_any_number_of_threads() {
    // The fault scenario: random bus faults, so each seed gives its own run.
    let base = Scenario::from_file(&scenario_file("faults.toml")).unwrap();
    let params = [
        Param::parse("gains.kp=1.0,1.4").unwrap(),
        Param::parse("plant.mass_kg=18..24").unwrap(),
    ];
    let runs = sweep::expand(&[1, 2, 3], &params).unwrap();
    let never = || false;
    let two = sweep::run_all(&base, &runs, 2, &never, |_| {}).unwrap();
    let one = sweep::run_all(&base, &runs, 1, &never, |_| {}).unwrap();
    assert_eq!(two.len(), 6);
    // Compared as the table's lines (a field that is NaN, "none", equals itself there).
    let csv = |rows: &[sweep::Row]| rows.iter().map(sweep::Row::csv).collect::<Vec<_>>();
    assert_eq!(csv(&one), csv(&two), "the same table on 1 and 2 threads");
    for (spec, row) in runs.iter().zip(&two) {
        let s = sweep::apply(&base, spec.seed, &spec.values).unwrap();
        let alone = sweep::run_one(&s, spec).unwrap();
        assert_eq!(alone.csv(), row.csv(), "run {}", spec.index);
    }
    // The seeds and values matter: not every row is the same.
    assert!(two.iter().any(|r| r.drift_max_m != two[0].drift_max_m));
    assert!(two.iter().any(|r| r.fault != "NONE"), "{two:#?}");
}

fn hostsim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_hostsim"))
}

/// `hostsim sweep square --seeds SEEDS --set plant.mass_kg=15..30`: a sweep with a drawn
/// parameter, for the tests to add to.
fn square_sweep(seeds: &str) -> Command {
    let mut c = hostsim();
    c.args([
        "sweep",
        "square",
        "--seeds",
        seeds,
        "--set",
        "plant.mass_kg=15..30",
    ]);
    c
}

#[test]
fn a_bad_name_or_value_fails_before_any_run() {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("sweep-bad");
    let _ = std::fs::remove_dir_all(&out);
    for (set, says) in [
        (
            "gains.kq=1,2",
            "gains.kq: no such field; [gains] has: ki, kp, kv",
        ),
        (
            "limits.max_current=16,-1",
            "the configuration refuses gains.kp=1, limits.max_current=-1: limits.max_current = -1",
        ),
        ("plant.mass_kg=0..20", "plant.mass_kg = "),
        ("gains.kp=1..x", "\"x\" is not a finite number"),
    ] {
        let o = hostsim()
            .args([
                "sweep",
                "square",
                "--seeds",
                "1..50",
                "--set",
                "gains.kp=1,2",
            ])
            .args(["--set", set, "--out"])
            .arg(&out)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{set}: {err}");
        assert!(err.contains(says), "{set}: {err}");
        assert!(!out.exists(), "{set}: nothing written, no run started");
    }
}

#[test]
fn ctrl_c_keeps_the_rows_finished() {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("sweep-interrupted");
    let _ = std::fs::remove_dir_all(&out);
    let mut child = hostsim()
        .args([
            "sweep",
            "square",
            "--seeds",
            "1..2000",
            "--jobs",
            "1",
            "--no-plot",
            "--out",
        ])
        .arg(&out)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Its first line comes once Ctrl-C is handled (not before: a fixed wait lost that race
    // on a loaded machine); the runs are under way 1.5 s later, and the one in flight ends.
    let mut stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    std::io::BufRead::read_line(&mut stderr, &mut line).unwrap();
    assert!(line.starts_with("sweep of"), "{line}");
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let killed = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let o = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(130), "{stdout}");
    assert!(stdout.contains("INTERRUPTED"), "{stdout}");
    // Not whole, so not renamed into place: the rows finished are in the `.part`.
    assert!(!out.join("sweep.csv").exists() && !out.join("sweep.jsonl").exists());
    assert!(stdout.contains("sweep.csv.part"), "{stdout}");
    let csv = std::fs::read_to_string(out.join("sweep.csv.part")).unwrap();
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert!(
        !rows.is_empty() && rows.len() < 2000,
        "{} rows finished",
        rows.len()
    );
    // Every row finished is complete, in index order, and the same as the run alone.
    let base = Scenario::builtin("square").unwrap();
    let first = sweep::run_one(
        &sweep::apply(&base, 1, &[]).unwrap(),
        &sweep::RunSpec {
            index: 0,
            seed: 1,
            values: vec![],
        },
    )
    .unwrap();
    assert_eq!(rows[0], first.csv());
    let indices: Vec<usize> = rows
        .iter()
        .map(|r| r.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert!(indices.windows(2).all(|w| w[0] < w[1]), "{indices:?}");
    let jsonl = std::fs::read_to_string(out.join("sweep.jsonl.part")).unwrap();
    assert_eq!(jsonl.lines().count(), rows.len());
}

#[test]
fn each_rows_command_runs_it_alone() {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("sweep-reproduce");
    let _ = std::fs::remove_dir_all(&out);
    let o = square_sweep("1..3")
        .args([
            "--set",
            "gains.kp=1.0,1.3",
            "--no-plot",
            "--worst",
            "6",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    let jsonl = std::fs::read_to_string(out.join("sweep.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = jsonl
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 6);
    // The printed command of each worst run gives the row's figures, bit for bit.
    let commands: Vec<&str> = stdout
        .lines()
        .filter_map(|l| l.split_once(": hostsim run ").map(|(_, c)| c))
        .collect();
    assert_eq!(commands.len(), 6, "{stdout}");
    for line in stdout.lines().filter(|l| l.contains(": hostsim run ")) {
        let index: usize = line.trim_start()[1..]
            .split(' ')
            .next()
            .unwrap()
            .parse()
            .unwrap();
        let command = line.split_once(": hostsim run ").unwrap().1;
        let alone = hostsim()
            .arg("run")
            .args(command.split(' '))
            .args(["--no-log", "--no-plot", "--json"])
            .output()
            .unwrap();
        assert!(alone.status.success(), "{command}");
        let summary: serde_json::Value = serde_json::from_slice(&alone.stdout).unwrap();
        assert_eq!(
            summary["max_position_error"], rows[index]["drift_max_m"],
            "{command}"
        );
        assert_eq!(summary["steps"], rows[index]["steps"], "{command}");
    }
}

/// [`square_sweep`] over two seeds with a grid too, into `out`, and `extra` arguments: its
/// stdout, or its stderr as the error.
fn sweep_into(out: &Path, extra: &[&str]) -> Result<String, String> {
    let o = square_sweep("1..2")
        .args(["--set", "gains.kp=1.0,1.3", "--no-plot", "--out"])
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    if o.status.success() {
        Ok(String::from_utf8_lossy(&o.stdout).into_owned())
    } else {
        Err(String::from_utf8_lossy(&o.stderr).into_owned())
    }
}

#[test]
fn shards_of_a_sweep_are_its_rows_byte_for_byte() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("sweep-shards");
    let _ = std::fs::remove_dir_all(&dir);
    let table = |name: &str| std::fs::read_to_string(dir.join(name).join("sweep.csv")).unwrap();
    sweep_into(&dir.join("whole"), &[]).unwrap();
    sweep_into(&dir.join("a"), &["--shard", "1/2"]).unwrap();
    sweep_into(&dir.join("b"), &["--shard", "2/2"]).unwrap();
    sweep_into(&dir.join("mid"), &["--runs", "1..2"]).unwrap();
    let whole = table("whole");
    let lines: Vec<&str> = whole.lines().collect();
    assert_eq!(lines.len(), 1 + 4, "{whole}");
    // The shards' rows after the one header, in order, are the whole table.
    let (a, b) = (table("a"), table("b"));
    let mut merged: Vec<&str> = a.lines().collect();
    merged.extend(b.lines().skip(1));
    assert_eq!(merged, lines);
    assert_eq!(
        table("mid").lines().skip(1).collect::<Vec<_>>(),
        lines[2..4]
    );
    // Bad parts fail before any run, naming the argument and the plan.
    for (args, says) in [
        (
            ["--runs", "3..9"],
            "--runs 3..9: the plan has rows 0..3 (4 runs)",
        ),
        (["--runs", "2..x"], "--runs: \"x\" is not a row index"),
        (["--shard", "0/2"], "--shard 0/2: K is 1 to N"),
        (["--shard", "1/5"], "N at most the plan's 4 runs"),
        (["--shard", "2"], "--shard \"2\": expected K/N"),
    ] {
        let e = sweep_into(&dir.join("bad"), &args).unwrap_err();
        assert!(e.contains(says), "{args:?}: {e}");
    }
    assert!(!dir.join("bad").join("sweep.csv").exists());
}

#[test]
fn merged_shards_are_the_whole_sweeps_files_and_parts_of_other_sweeps_are_refused() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("sweep-merge");
    let _ = std::fs::remove_dir_all(&dir);
    let plotted = |out: &str, extra: &[&str]| {
        let o = square_sweep("1..3")
            .arg("--out")
            .arg(dir.join(out))
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    plotted("whole", &[]);
    for k in 1..=3 {
        plotted(
            &format!("part{k}"),
            &["--shard", &format!("{k}/3"), "--no-plot"],
        );
    }
    let merge = |parts: &[&str], out: &str| {
        let mut c = hostsim();
        c.args(["sweep", "--merge"]);
        for p in parts {
            c.arg(dir.join(p));
        }
        c.arg("--out").arg(dir.join(out)).output().unwrap()
    };
    // In any order of the folders.
    let o = merge(&["part3", "part1", "part2"], "merged");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for file in ["sweep.csv", "sweep.jsonl", "sweep.png", "sweep.plan.json"] {
        let (a, b) = (
            std::fs::read(dir.join("whole").join(file)).unwrap(),
            std::fs::read(dir.join("merged").join(file)).unwrap(),
        );
        assert!(
            a == b,
            "{file}: the merged file differs from the whole sweep's"
        );
    }
    // A part missing, a part twice, a part of another sweep: refused, nothing written.
    plotted(
        "other",
        &["--shard", "1/3", "--no-plot", "--set", "gains.kp=1.1"],
    );
    for (parts, says) in [
        (
            &["part1", "part2"][..],
            "row 2 of 3 is in none of the parts",
        ),
        (
            &["part1", "part1", "part2", "part3"][..],
            "row 0 is in two parts",
        ),
        (&["other", "part2", "part3"][..], "a part of another sweep"),
    ] {
        let o = merge(parts, "bad");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(says), "{parts:?}: {e}");
        assert!(!dir.join("bad").join("sweep.csv").exists());
    }
}
