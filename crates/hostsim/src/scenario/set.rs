//! `--set KEY=VALUE`: one field of a scenario's drive configuration (as its TOML names it,
//! `gains.kp`), of its simulated robot (`plant.mass_kg`), of its pod node (`pods.noise`, the
//! block's `pods.radius_error` and `pods.misalignment_deg`, a pod's own
//! `pods.pod[1].offset_x`) or of its IMU (`imu.bias_deg_s`) changed, checked as a file would
//! be. `hostsim run --set` and every run of `hostsim sweep` go through here.

use firmware::Config;

use super::Scenario;
use crate::nodes::drives::SimDrives;
use crate::nodes::imu::ImuParams;
use crate::nodes::plant::PlantSpec;
use crate::nodes::pods::{PodErrors, PodsParams};

/// Why a value cannot be set.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SetError {
    /// The configuration cannot be written as TOML (a bug: it came from TOML).
    #[error("configuration: {0}")]
    Syntax(String),
    /// A parameter name that names nothing.
    #[error("{key}: no such field; {hint}")]
    UnknownField {
        /// The name as given.
        key: String,
        /// The names that exist there.
        hint: String,
    },
    /// Values the drive configuration's validation refuses.
    #[error("the configuration refuses {values}: {why}")]
    Refused {
        /// The values set, `k=v, ...`.
        values: String,
        /// The configuration's reason, naming the field and value.
        why: String,
    },
    /// A value the plant refuses.
    #[error("{key} = {value}: {why}")]
    Invalid {
        /// The name.
        key: String,
        /// The value.
        value: f64,
        /// The configuration's or the plant's reason.
        why: String,
    },
}

impl SetError {
    /// [`SetError::UnknownField`]: `key` names nothing; `hint` says what there is.
    fn unknown(key: &str, hint: impl Into<String>) -> Self {
        Self::UnknownField {
            key: key.to_string(),
            hint: hint.into(),
        }
    }
}

impl Scenario {
    /// This scenario with `values` set (`plant.*` on the robot, `pods.*` on its pod node,
    /// `imu.*` on its IMU, every other name on the drive configuration) and its seed `seed`.
    ///
    /// # Errors
    /// [`SetError::UnknownField`] for a name that names nothing, [`SetError::Refused`] or
    /// [`SetError::Invalid`] for a value the configuration's validation or the plant refuses.
    pub fn with_values(&self, seed: u64, values: &[(String, f64)]) -> Result<Self, SetError> {
        let mut s = self.clone();
        s.seed = seed;
        let mut config: toml::Table = toml::from_str(&s.config.to_toml_string())
            .map_err(|e| SetError::Syntax(e.to_string()))?;
        let mut config_changed = false;
        for (key, value) in values {
            if let Some(field) = key.strip_prefix("plant.") {
                set_plant(&mut s.plant, key, field, *value)?;
            } else if let Some(field) = key.strip_prefix("pods.") {
                let configured = s.config.odometry.pods.len();
                set_pods(s.pods.as_mut(), configured, key, field, *value)?;
            } else if let Some(field) = key.strip_prefix("imu.") {
                set_imu(s.imu.as_mut(), key, field, *value)?;
            } else {
                set_config(&mut config, key, *value)?;
                config_changed = true;
            }
        }
        if config_changed {
            let text = toml::to_string(&config).unwrap_or_default();
            s.config = Config::from_toml_str(&text).map_err(|e| SetError::Refused {
                values: values
                    .iter()
                    .filter(|(k, _)| !k.starts_with("plant."))
                    .map(|(k, v)| format!("{k}={v}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                why: match e {
                    firmware::config::LoadError::Invalid { source, .. } => source.to_string(),
                    other => other.to_string(),
                },
            })?;
        }
        if let Some((field, value, expected)) = s.pods.as_ref().and_then(|p| p.invalid()) {
            return Err(SetError::Invalid {
                key: format!("pods.{field}"),
                value,
                why: format!("expected {expected}"),
            });
        }
        if let Some((field, value, expected)) = s.imu.as_ref().and_then(|i| i.invalid()) {
            return Err(SetError::Invalid {
                key: format!("imu.{field}"),
                value,
                why: format!("expected {expected}"),
            });
        }
        if let Some((field, value, expected)) = s.plant.first_invalid() {
            return Err(SetError::Invalid {
                key: field.to_string(),
                value,
                why: format!("expected {expected}"),
            });
        }
        SimDrives::with_spec(&s.config, &s.plant).map_err(|e| SetError::Invalid {
            key: e.field.to_string(),
            value: e.value,
            why: format!("the plant refuses it: expected {}", e.expected),
        })?;
        Ok(s)
    }
}

/// The `plant.*` names a sweep can set.
pub const PLANT_FIELDS: [&str; 5] = ["wheel_radius", "lx", "ly", "roller_drag", "mass_kg"];

fn set_plant(plant: &mut PlantSpec, key: &str, field: &str, value: f64) -> Result<(), SetError> {
    let slot = match field {
        "wheel_radius" => &mut plant.wheel_radius,
        "lx" => &mut plant.lx,
        "ly" => &mut plant.ly,
        "roller_drag" => &mut plant.roller_drag,
        "mass_kg" => &mut plant.mass_kg,
        _ => {
            return Err(SetError::unknown(
                key,
                format!("plant fields: {}", PLANT_FIELDS.join(", ")),
            ));
        }
    };
    *slot = Some(value);
    Ok(())
}

/// The `pods.*` names a sweep can set: the pod node's noise, the block's errors, and each
/// pod's own (`pods.pod[I].<field>`, I from 0 in the configuration's order).
pub const PODS_FIELDS: [&str; 3] = ["noise", "radius_error", "misalignment_deg"];
/// The fields of one pod, `pods.pod[I].<field>`.
pub const POD_FIELDS: [&str; 4] = ["radius_error", "misalignment_deg", "offset_x", "offset_y"];
/// The `imu.*` names a sweep can set.
pub const IMU_FIELDS: [&str; 2] = ["bias_deg_s", "noise_density"];

fn set_pods(
    pods: Option<&mut PodsParams>,
    configured: usize,
    key: &str,
    field: &str,
    value: f64,
) -> Result<(), SetError> {
    let unknown = |hint: String| SetError::unknown(key, hint);
    let Some(pods) = pods else {
        return Err(unknown(
            "the scenario has no [pods] table (no pod node: scenarios/square_60s_pods.toml has one)"
                .into(),
        ));
    };
    let fields = || {
        format!(
            "pods fields: {}, and pod[I].{{{}}} for I in 0..{configured}",
            PODS_FIELDS.join(", "),
            POD_FIELDS.join(", ")
        )
    };
    let slot = match field {
        "noise" => &mut pods.noise,
        "radius_error" => &mut pods.radius_error,
        "misalignment_deg" => &mut pods.misalignment_deg,
        _ => {
            let (index, pod_field) = field
                .strip_prefix("pod[")
                .and_then(|rest| rest.split_once("]."))
                .ok_or_else(|| unknown(fields()))?;
            let i: usize = index.parse().map_err(|_| unknown(fields()))?;
            if i >= configured {
                return Err(unknown(format!(
                    "the configuration has {configured} pods ([[odometry.pods]]): pod[0] to pod[{}]",
                    configured.saturating_sub(1)
                )));
            }
            if pods.pod.len() <= i {
                pods.pod.resize(i + 1, PodErrors::default());
            }
            let pod = &mut pods.pod[i];
            match pod_field {
                "radius_error" => &mut pod.radius_error,
                "misalignment_deg" => &mut pod.misalignment_deg,
                "offset_x" => &mut pod.offset_x,
                "offset_y" => &mut pod.offset_y,
                _ => return Err(unknown(fields())),
            }
        }
    };
    *slot = value;
    Ok(())
}

fn set_imu(
    imu: Option<&mut ImuParams>,
    key: &str,
    field: &str,
    value: f64,
) -> Result<(), SetError> {
    let unknown = |hint: String| SetError::unknown(key, hint);
    let Some(imu) = imu else {
        return Err(unknown(
            "the scenario has no [imu] table (no IMU node)".into(),
        ));
    };
    let slot = match field {
        "bias_deg_s" => &mut imu.bias_deg_s,
        "noise_density" => &mut imu.noise_density,
        _ => return Err(unknown(format!("imu fields: {}", IMU_FIELDS.join(", ")))),
    };
    *slot = value;
    Ok(())
}

fn set_config(config: &mut toml::Table, key: &str, value: f64) -> Result<(), SetError> {
    let unknown = |table: &toml::Table, at: &str| {
        SetError::unknown(
            key,
            format!(
                "{at} has: {}",
                table.keys().cloned().collect::<Vec<_>>().join(", ")
            ),
        )
    };
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().unwrap_or_default();
    let mut table = config;
    let mut at = String::from("the configuration");
    for part in parts {
        if !table.get(part).is_some_and(toml::Value::is_table) {
            return Err(unknown(table, &at));
        }
        at = format!(
            "[{}]",
            key.split('.')
                .take_while(|p| *p != last)
                .collect::<Vec<_>>()
                .join(".")
        );
        table = match table.get_mut(part) {
            Some(toml::Value::Table(t)) => t,
            _ => unreachable!("checked above"),
        };
    }
    let new = match table.get(last) {
        Some(toml::Value::Float(_)) => toml::Value::Float(value),
        #[allow(clippy::cast_possible_truncation)]
        Some(toml::Value::Integer(_)) if value.fract() == 0.0 => toml::Value::Integer(value as i64),
        Some(toml::Value::Integer(_)) => {
            return Err(SetError::Invalid {
                key: key.to_string(),
                value,
                why: "expected a whole number".into(),
            });
        }
        Some(_) => {
            return Err(SetError::Invalid {
                key: key.to_string(),
                value,
                why: "not a number field: a sweep sets numbers".into(),
            });
        }
        None => return Err(unknown(table, &at)),
    };
    table.insert(last.to_string(), new);
    Ok(())
}
