//! `hostsim kin`: a kinematics calculator for scripts, one JSON object per line.
//!
//! ```text
//! {"op":"inverse","lx":0.2,"ly":0.15,"r":0.05,"vx":1,"vy":0,"wz":0}  ->  {"fl":20,"fr":20,"rl":20,"rr":20}
//! {"op":"forward","lx":0.2,"ly":0.15,"r":0.05,"fl":20,"fr":20,"rl":20,"rr":20}  ->  {"vx":1,"vy":0,"wz":0}
//! ```
//!
//! Wheel speeds in rad/s (FL, FR, RL, RR), body twist in m/s and rad/s (x forward, y left,
//! counter-clockwise), standard layout with wheels at `(±lx, ±ly)` and radius `r`. A line that
//! cannot be answered gives `{"error":"..."}` naming the field and the value, and the next line
//! is read as usual. Blank lines are skipped.

use std::io::{BufRead, Write};

use kinematics::{ChassisVelocity, MecanumKinematics, WheelSpeeds};
use serde_json::{Map, Value, json};

fn number(obj: &Map<String, Value>, key: &str) -> Result<f64, String> {
    match obj.get(key) {
        None => Err(format!("missing field \"{key}\"")),
        Some(v) => match v.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(format!("field \"{key}\" must be a finite number, got {v}")),
        },
    }
}

/// Answers one input line (without its newline) with one output line.
#[must_use]
pub fn answer(line: &str) -> String {
    match compute(line) {
        Ok(v) => v.to_string(),
        Err(e) => json!({ "error": e }).to_string(),
    }
}

fn compute(line: &str) -> Result<Value, String> {
    let value: Value = serde_json::from_str(line).map_err(|e| format!("not JSON: {e}"))?;
    let obj = value
        .as_object()
        .ok_or_else(|| "expected a JSON object".to_string())?;
    let op = obj
        .get("op")
        .and_then(Value::as_str)
        .ok_or_else(|| "missing field \"op\" (\"inverse\" or \"forward\")".to_string())?;
    let (lx, ly, r) = (number(obj, "lx")?, number(obj, "ly")?, number(obj, "r")?);
    let kin = MecanumKinematics::<f64, 4>::standard(lx, ly, r).map_err(|e| e.to_string())?;
    match op {
        "inverse" => {
            let v =
                ChassisVelocity::new(number(obj, "vx")?, number(obj, "vy")?, number(obj, "wz")?);
            let w = kin.inverse(v);
            Ok(json!({ "fl": w.fl(), "fr": w.fr(), "rl": w.rl(), "rr": w.rr() }))
        }
        "forward" => {
            let w = WheelSpeeds::new(
                number(obj, "fl")?,
                number(obj, "fr")?,
                number(obj, "rl")?,
                number(obj, "rr")?,
            );
            let v = kin.forward(&w);
            Ok(json!({ "vx": v.vx, "vy": v.vy, "wz": v.wz }))
        }
        other => Err(format!(
            "unknown op {other:?}: expected \"inverse\" or \"forward\""
        )),
    }
}

/// Reads lines from `input` and writes one answer per non-blank line to `output`, flushing
/// after each so a script can talk to it line by line.
///
/// # Errors
/// I/O errors of the streams.
pub fn run(input: impl BufRead, mut output: impl Write) -> std::io::Result<()> {
    for line in input.lines() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        writeln!(output, "{}", answer(&line))?;
        output.flush()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(out: &str, key: &str) -> f64 {
        let v: Value = serde_json::from_str(out).unwrap();
        v[key].as_f64().unwrap_or_else(|| panic!("{key} in {out}"))
    }

    #[test]
    fn inverse_and_forward_match_the_seed_example() {
        // Seed 002: 0.22, 0.11 m/s, 30 mm wheels -> 3.66, 11, 11, 3.66 rad/s.
        let out =
            answer(r#"{"op":"inverse","lx":0.1,"ly":0.075,"r":0.03,"vx":0.22,"vy":0.11,"wz":0}"#);
        for (k, want) in [("fl", 3.6667), ("fr", 11.0), ("rl", 11.0), ("rr", 3.6667)] {
            assert!((field(&out, k) - want).abs() < 1e-3, "{out}");
        }
        let out = answer(
            r#"{"op":"forward","lx":0.1,"ly":0.075,"r":0.03,"fl":3.6666666666666665,"fr":11,"rl":11,"rr":3.6666666666666665}"#,
        );
        assert!((field(&out, "vx") - 0.22).abs() < 1e-12, "{out}");
        assert!((field(&out, "vy") - 0.11).abs() < 1e-12, "{out}");
        assert!(field(&out, "wz").abs() < 1e-12, "{out}");
    }

    #[test]
    fn bad_lines_give_errors_and_the_rest_go_on() {
        let input = "{\"op\":\"inverse\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05,\"vx\":1,\"vy\":0,\"wz\":0}\n\
                     not json\n\
                     \n\
                     {\"op\":\"inverse\",\"lx\":0.2,\"ly\":0.15,\"r\":-1,\"vx\":1,\"vy\":0,\"wz\":0}\n\
                     {\"op\":\"forward\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05,\"fl\":1,\"fr\":\"x\",\"rl\":1,\"rr\":1}\n\
                     {\"op\":\"sideways\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05}\n\
                     {\"op\":\"forward\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05,\"fl\":20,\"fr\":20,\"rl\":20,\"rr\":20}\n";
        let mut out = Vec::new();
        run(input.as_bytes(), &mut out).unwrap();
        let lines: Vec<&str> = std::str::from_utf8(&out).unwrap().lines().collect();
        assert_eq!(lines.len(), 6, "{lines:?}");
        assert!((field(lines[0], "fl") - 20.0).abs() < 1e-12);
        assert!(lines[1].contains("\"error\"") && lines[1].contains("not JSON"));
        assert!(lines[2].contains("radius -1"), "{}", lines[2]);
        assert!(lines[3].contains("\\\"fr\\\""), "{}", lines[3]);
        assert!(lines[4].contains("sideways"), "{}", lines[4]);
        assert!((field(lines[5], "vx") - 1.0).abs() < 1e-12);
    }
}
