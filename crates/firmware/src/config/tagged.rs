//! Reading `[geometry]` and `[drive]`, tables whose variant a key names (`layout`,
//! `protocol`), value by value.
//!
//! Serde's derive for such an internally tagged enum reads the whole table into a buffer
//! before it knows the variant, so a wrong value inside (`lx = "0.20"`) was reported at the
//! table. Here every value is read straight from the deserializer, the tag wherever it stands,
//! so the error points at its key; the rules are the derive's (unknown, missing and duplicate
//! keys, the variant's own keys only).

use core::fmt;
use core::marker::PhantomData;

use serde::de::{self, DeserializeSeed, MapAccess, Visitor};
use serde::{Deserialize, Deserializer};

use super::{Cia402Drive, Drive, Geometry, cia402_defaults, esc_model_serde, unit};

/// A tag's value: a variant, which takes its own keys.
trait Tag: for<'de> Deserialize<'de> + Copy {
    /// The tag's key (`layout`).
    const KEY: &'static str;
    /// Every key of the table: the tag's, then each variant's (at most 32), in the order an
    /// unknown key's error lists them before the tag is read.
    const ALL: &'static [&'static str];
    /// The keys of this variant, besides the tag.
    fn keys(self) -> &'static [&'static str];
}

/// The keys of one tagged table as they are read: each one a variant takes, once.
struct Table<T> {
    tag: Option<T>,
    /// The keys read, by their bit in [`Tag::ALL`].
    seen: u32,
}

impl<T: Tag> Table<T> {
    const fn new() -> Self {
        Self { tag: None, seen: 0 }
    }

    /// The next key other than the tag (whose value it reads), or `None` at the table's end.
    fn next_key<'de, A: MapAccess<'de>>(
        &mut self,
        map: &mut A,
    ) -> Result<Option<&'static str>, A::Error> {
        loop {
            let seed = KeySeed {
                takes: self.tag.map(T::keys),
                _tag: PhantomData::<T>,
            };
            let Some((key, bit)) = map.next_key_seed(seed)? else {
                return Ok(None);
            };
            if self.seen & bit != 0 {
                return Err(de::Error::duplicate_field(key));
            }
            self.seen |= bit;
            if key != T::KEY {
                return Ok(Some(key));
            }
            self.tag = Some(map.next_value()?);
        }
    }

    /// After the last key: the variant, if it was named and takes every key that was given.
    fn finish<E: de::Error>(&self) -> Result<T, E> {
        let tag = self.tag.ok_or_else(|| E::missing_field(T::KEY))?;
        let takes = tag.keys();
        for (i, key) in T::ALL.iter().enumerate() {
            if self.seen & (1 << i) != 0 && *key != T::KEY && !takes.contains(key) {
                return Err(E::unknown_field(key, takes));
            }
        }
        Ok(tag)
    }
}

/// One key: one of [`Tag::ALL`] (of the variant's, once the tag is read), with its bit.
struct KeySeed<T> {
    takes: Option<&'static [&'static str]>,
    _tag: PhantomData<T>,
}

impl<'de, T: Tag> DeserializeSeed<'de> for KeySeed<T> {
    type Value = (&'static str, u32);

    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_identifier(self)
    }
}

impl<T: Tag> Visitor<'_> for KeySeed<T> {
    type Value = (&'static str, u32);

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a key")
    }

    fn visit_str<E: de::Error>(self, key: &str) -> Result<Self::Value, E> {
        let taken = key == T::KEY || self.takes.is_none_or(|takes| takes.contains(&key));
        match T::ALL.iter().position(|k| *k == key) {
            Some(i) if taken => Ok((T::ALL[i], 1 << i)),
            _ => Err(E::unknown_field(key, self.takes.unwrap_or(T::ALL))),
        }
    }
}

/// A key the variant needs.
fn required<T, E: de::Error>(value: Option<T>, key: &'static str) -> Result<T, E> {
    value.ok_or_else(|| E::missing_field(key))
}

/// `[geometry] layout`.
#[derive(Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Layout {
    Standard,
    General,
}

const EFFECTIVENESS: [&str; 3] = [
    "forward_effectiveness",
    "lateral_effectiveness",
    "yaw_effectiveness",
];

impl Tag for Layout {
    const KEY: &'static str = "layout";
    const ALL: &'static [&'static str] = &[
        "layout",
        "lx",
        "ly",
        "wheel_radius",
        "wheels",
        EFFECTIVENESS[0],
        EFFECTIVENESS[1],
        EFFECTIVENESS[2],
    ];

    fn keys(self) -> &'static [&'static str] {
        match self {
            Self::Standard => &[
                "lx",
                "ly",
                "wheel_radius",
                EFFECTIVENESS[0],
                EFFECTIVENESS[1],
                EFFECTIVENESS[2],
            ],
            Self::General => &[
                "wheels",
                EFFECTIVENESS[0],
                EFFECTIVENESS[1],
                EFFECTIVENESS[2],
            ],
        }
    }
}

impl<'de> Deserialize<'de> for Geometry {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Geometry;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a table with `layout`")
            }

            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Geometry, A::Error> {
                let mut table = Table::<Layout>::new();
                let (mut lx, mut ly, mut wheel_radius, mut wheels) = (None, None, None, None);
                let mut factors = [None; 3];
                while let Some(key) = table.next_key(&mut map)? {
                    match key {
                        "lx" => lx = Some(map.next_value()?),
                        "ly" => ly = Some(map.next_value()?),
                        "wheel_radius" => wheel_radius = Some(map.next_value()?),
                        "wheels" => wheels = Some(map.next_value()?),
                        _ => match EFFECTIVENESS.iter().position(|k| *k == key) {
                            Some(i) => factors[i] = Some(map.next_value()?),
                            None => return Err(de::Error::unknown_field(key, Layout::ALL)),
                        },
                    }
                }
                let [
                    forward_effectiveness,
                    lateral_effectiveness,
                    yaw_effectiveness,
                ] = factors.map(|f| f.unwrap_or_else(unit::one));
                Ok(match table.finish()? {
                    Layout::Standard => Geometry::Standard {
                        lx: required(lx, "lx")?,
                        ly: required(ly, "ly")?,
                        wheel_radius: required(wheel_radius, "wheel_radius")?,
                        forward_effectiveness,
                        lateral_effectiveness,
                        yaw_effectiveness,
                    },
                    Layout::General => Geometry::General {
                        wheels: required(wheels, "wheels")?,
                        forward_effectiveness,
                        lateral_effectiveness,
                        yaw_effectiveness,
                    },
                })
            }
        }
        d.deserialize_map(V)
    }
}

/// `[drive] protocol`.
#[derive(Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Protocol {
    Dji,
    Odrive,
    Cia402,
}

impl Tag for Protocol {
    const KEY: &'static str = "protocol";
    const ALL: &'static [&'static str] = &[
        "protocol",
        "model",
        "esc_ids",
        "gear_ratio",
        "inverted",
        "node_ids",
        "vel_ramp",
        "axes",
        "target_rpm_per_unit",
        "actual_rpm_per_unit",
        "master_node",
        "heartbeat_ms",
        "heartbeat_timeout_ms",
    ];

    fn keys(self) -> &'static [&'static str] {
        match self {
            Self::Dji => &["model", "esc_ids", "gear_ratio", "inverted"],
            Self::Odrive => &["node_ids", "gear_ratio", "inverted", "vel_ramp"],
            Self::Cia402 => &[
                "node_ids",
                "axes",
                "gear_ratio",
                "inverted",
                "target_rpm_per_unit",
                "actual_rpm_per_unit",
                "master_node",
                "heartbeat_ms",
                "heartbeat_timeout_ms",
            ],
        }
    }
}

impl<'de> Deserialize<'de> for Drive {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Drive;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a table with `protocol`")
            }

            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Drive, A::Error> {
                let mut table = Table::<Protocol>::new();
                let (mut model, mut esc_ids, mut node_ids, mut axes) = (None, None, None, None);
                let (mut gear_ratio, mut inverted, mut vel_ramp) = (None, None, None);
                let (mut target_rpm_per_unit, mut actual_rpm_per_unit) = (None, None);
                let (mut master_node, mut heartbeat_ms, mut heartbeat_timeout_ms) =
                    (None, None, None);
                while let Some(key) = table.next_key(&mut map)? {
                    match key {
                        "model" => model = Some(map.next_value::<esc_model_serde::Model>()?.0),
                        "esc_ids" => esc_ids = Some(map.next_value()?),
                        "node_ids" => node_ids = Some(map.next_value()?),
                        "axes" => axes = Some(map.next_value()?),
                        "gear_ratio" => gear_ratio = Some(map.next_value()?),
                        "inverted" => inverted = Some(map.next_value()?),
                        "vel_ramp" => vel_ramp = Some(map.next_value()?),
                        "target_rpm_per_unit" => target_rpm_per_unit = Some(map.next_value()?),
                        "actual_rpm_per_unit" => actual_rpm_per_unit = Some(map.next_value()?),
                        "master_node" => master_node = Some(map.next_value()?),
                        "heartbeat_ms" => heartbeat_ms = Some(map.next_value()?),
                        "heartbeat_timeout_ms" => heartbeat_timeout_ms = Some(map.next_value()?),
                        _ => return Err(de::Error::unknown_field(key, Protocol::ALL)),
                    }
                }
                Ok(match table.finish()? {
                    Protocol::Dji => Drive::Dji {
                        model: required(model, "model")?,
                        esc_ids: required(esc_ids, "esc_ids")?,
                        gear_ratio: required(gear_ratio, "gear_ratio")?,
                        inverted: required(inverted, "inverted")?,
                    },
                    Protocol::Odrive => Drive::Odrive {
                        node_ids: required(node_ids, "node_ids")?,
                        gear_ratio: required(gear_ratio, "gear_ratio")?,
                        inverted: required(inverted, "inverted")?,
                        vel_ramp: vel_ramp.unwrap_or_default(),
                    },
                    Protocol::Cia402 => Drive::Cia402(Cia402Drive {
                        node_ids: required(node_ids, "node_ids")?,
                        axes: required(axes, "axes")?,
                        gear_ratio: required(gear_ratio, "gear_ratio")?,
                        inverted: required(inverted, "inverted")?,
                        target_rpm_per_unit: required(target_rpm_per_unit, "target_rpm_per_unit")?,
                        actual_rpm_per_unit: required(actual_rpm_per_unit, "actual_rpm_per_unit")?,
                        master_node: master_node.unwrap_or_else(cia402_defaults::master_node),
                        heartbeat_ms: heartbeat_ms.unwrap_or_else(cia402_defaults::heartbeat_ms),
                        heartbeat_timeout_ms: heartbeat_timeout_ms
                            .unwrap_or_else(cia402_defaults::heartbeat_timeout_ms),
                    }),
                })
            }
        }
        d.deserialize_map(V)
    }
}

#[cfg(test)]
mod tests {
    use super::{Layout, Protocol, Tag};

    /// `ALL` is the tag and the union of the variants' keys, and fits the 32 bits of `seen`.
    #[test]
    fn every_key_is_listed_once() {
        fn check<T: Tag>(variants: &[T]) {
            assert!(T::ALL.len() <= 32);
            assert_eq!(T::ALL[0], T::KEY);
            for (i, key) in T::ALL.iter().enumerate() {
                assert!(!T::ALL[..i].contains(key), "{key} twice");
                let used = variants.iter().any(|v| v.keys().contains(key));
                assert_eq!(used, i > 0, "{key}");
            }
            for v in variants {
                assert!(v.keys().iter().all(|k| T::ALL.contains(k)));
            }
        }
        check(&[Layout::Standard, Layout::General]);
        check(&[Protocol::Dji, Protocol::Odrive, Protocol::Cia402]);
    }
}
