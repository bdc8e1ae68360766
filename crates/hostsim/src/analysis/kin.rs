//! `hostsim kin`: a kinematics calculator for scripts, one JSON object per line.
//!
//! ```text
//! {"op":"inverse","lx":0.2,"ly":0.15,"r":0.05,"vx":1,"vy":0,"wz":0}  ->  {"fl":20,"fr":20,"rl":20,"rr":20}
//! {"op":"forward","lx":0.2,"ly":0.15,"r":0.05,"fl":20,"fr":20,"rl":20,"rr":20}  ->  {"vx":1,"vy":0,"wz":0}
//! ```
//!
//! Wheel speeds in rad/s (FL, FR, RL, RR), body twist in m/s and rad/s (x forward, y left,
//! counter-clockwise), standard layout with the wheel contacts at `(±lx, ±ly)` metres from the
//! centre (half the wheelbase, half the track; both > 0) and wheel radius `r` metres (> 0). A
//! line that cannot be answered (not JSON, not UTF-8, a missing, bad or unknown field, a
//! result too large to be finite) gives `{"error":"..."}` naming the field and the value,
//! and the next line is read as usual. Blank lines are skipped, without an answer.

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

/// A field that must be a finite number greater than zero.
fn positive(obj: &Map<String, Value>, key: &str, what: &str) -> Result<f64, String> {
    let x = number(obj, key)?;
    if x > 0.0 {
        Ok(x)
    } else {
        Err(format!("field \"{key}\" ({what}) must be > 0, got {x}"))
    }
}

/// The answer's values, or an error if one is not finite (inputs too large).
fn finite_object(fields: &[(&str, f64)]) -> Result<Value, String> {
    if let Some((key, x)) = fields.iter().find(|(_, x)| !x.is_finite()) {
        return Err(format!(
            "result \"{key}\" is not finite ({x}): the inputs are too large"
        ));
    }
    Ok(Value::Object(
        fields
            .iter()
            .map(|&(k, x)| (k.to_string(), json!(x)))
            .collect(),
    ))
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
    let (inverse, fields): (bool, &[&str]) = match op {
        "inverse" => (true, &["op", "lx", "ly", "r", "vx", "vy", "wz"]),
        "forward" => (false, &["op", "lx", "ly", "r", "fl", "fr", "rl", "rr"]),
        other => {
            return Err(format!(
                "unknown op {other:?}: expected \"inverse\" or \"forward\""
            ));
        }
    };
    // A field the op does not take is a mistake (a typo, or a forward input sent as inverse).
    if let Some(key) = obj.keys().find(|k| !fields.contains(&k.as_str())) {
        return Err(format!(
            "unknown field {key:?} for op {op:?}: it takes {}",
            fields.join(", ")
        ));
    }
    let lx = positive(obj, "lx", "centre to wheel along x, m")?;
    let ly = positive(obj, "ly", "centre to wheel along y, m")?;
    let r = positive(obj, "r", "wheel radius, m")?;
    let kin = MecanumKinematics::<f64, 4>::standard(lx, ly, r).map_err(|e| e.to_string())?;
    if inverse {
        let v = ChassisVelocity::new(number(obj, "vx")?, number(obj, "vy")?, number(obj, "wz")?);
        let w = kin.inverse(v);
        finite_object(&[
            ("fl", w.fl()),
            ("fr", w.fr()),
            ("rl", w.rl()),
            ("rr", w.rr()),
        ])
    } else {
        let w = WheelSpeeds::new(
            number(obj, "fl")?,
            number(obj, "fr")?,
            number(obj, "rl")?,
            number(obj, "rr")?,
        );
        let v = kin.forward(&w);
        finite_object(&[("vx", v.vx), ("vy", v.vy), ("wz", v.wz)])
    }
}

/// Reads lines from `input` and writes one answer per non-blank line to `output`, flushing
/// after each so a script can talk to it line by line. A line that is not UTF-8 is answered
/// with an error like any other bad line.
///
/// # Errors
/// I/O errors of the streams.
pub fn run(input: impl BufRead, mut output: impl Write) -> std::io::Result<()> {
    for (n, line) in input.split(b'\n').enumerate() {
        let line = line?;
        let line = line.strip_suffix(b"\r").unwrap_or(&line);
        let answer = match std::str::from_utf8(line) {
            Ok(text) if text.trim().is_empty() => continue,
            Ok(text) => answer(text),
            Err(e) => json!({ "error": format!("line {} is not UTF-8: {e}", n + 1) }).to_string(),
        };
        writeln!(output, "{answer}")?;
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
    fn inverse_and_forward_match_the_worked_example() {
        // The documentation page's worked example (kinematics README, References): 0.22, 0.11 m/s,
        // 30 mm wheels -> 3.66, 11, 11, 3.66 rad/s.
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
                     {\"op\":\"forward\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05,\"fl\":1,\"fr\":1,\"rl\":1,\"rr\":1,\"vx\":1}\n\
                     {\"op\":\"forward\",\"lx\":0.2,\"ly\":0.15,\"r\":0.05,\"fl\":20,\"fr\":20,\"rl\":20,\"rr\":20}\n";
        let mut out = Vec::new();
        run(input.as_bytes(), &mut out).unwrap();
        let lines: Vec<&str> = std::str::from_utf8(&out).unwrap().lines().collect();
        assert_eq!(lines.len(), 7, "{lines:?}");
        assert!((field(lines[0], "fl") - 20.0).abs() < 1e-12);
        assert!(lines[1].contains("\"error\"") && lines[1].contains("not JSON"));
        assert!(
            lines[2].contains("\\\"r\\\"") && lines[2].contains("-1"),
            "{}",
            lines[2]
        );
        assert!(lines[3].contains("\\\"fr\\\""), "{}", lines[3]);
        assert!(lines[4].contains("sideways"), "{}", lines[4]);
        assert!(
            lines[5].contains("unknown field \\\"vx\\\" for op \\\"forward\\\""),
            "{}",
            lines[5]
        );
        assert!((field(lines[6], "vx") - 1.0).abs() < 1e-12);
    }

    #[test]
    fn bad_geometry_overflow_and_bad_bytes_are_answered_with_errors() {
        let inverse = |lx: &str, ly: &str, r: &str, vx: &str| {
            format!(r#"{{"op":"inverse","lx":{lx},"ly":{ly},"r":{r},"vx":{vx},"vy":0,"wz":1}}"#)
        };
        for (line, field) in [
            (inverse("0.2", "-0.15", "0.05", "0"), "ly"),
            (inverse("0", "0.15", "0.05", "0"), "lx"),
            (inverse("0.2", "0.15", "0", "0"), "r"),
        ] {
            let out = answer(&line);
            assert!(out.contains(&format!("\\\"{field}\\\"")), "{out}");
            assert!(out.contains("must be > 0"), "{out}");
        }
        let out = answer(&inverse("0.2", "0.15", "1e-10", "1e300"));
        assert!(out.contains("not finite"), "{out}");

        let mut input = b"\xff\n".to_vec();
        input.extend(inverse("0.2", "0.15", "0.05", "1").as_bytes());
        input.extend(b"\r\n");
        let mut out = Vec::new();
        run(input.as_slice(), &mut out).unwrap();
        let lines: Vec<&str> = std::str::from_utf8(&out).unwrap().lines().collect();
        assert_eq!(lines.len(), 2, "{lines:?}");
        assert!(lines[0].contains("line 1 is not UTF-8"), "{}", lines[0]);
        // vx 1, wz 1: FL = (1 - 0.35) / 0.05 = 13 rad/s.
        assert!((field(lines[1], "fl") - 13.0).abs() < 1e-9, "{}", lines[1]);
    }
}
