//! `params`: the robot's parameters (`firmware::params::PARAMS`) as JSON lines, with a
//! configuration's values, or as the robot's EDS (`dbc/mecanum_robot.eds`).

use std::fmt::Write as _;
use std::io::{self, Write as _};
use std::path::Path;

use firmware::Config;
use firmware::control::{INFO, INFO_INDEX, RESTORE, STORE};
use firmware::params::{Change, PARAMS, Param, ParamType};
use firmware::protocol::robot::PROTOCOL_VERSION;
use serde::Serialize;

/// One parameter's JSON line.
#[derive(Serialize)]
struct Line<'a> {
    name: &'a str,
    index: u16,
    sub: u8,
    #[serde(rename = "type")]
    ty: &'static str,
    unit: &'a str,
    low: f64,
    /// `None` (null) where the parameter has no upper bound (`inf` is a setting).
    high: Option<f64>,
    change: &'static str,
    doc: &'a str,
    /// The configuration's value; absent without `--config`, null where it has no such field.
    #[serde(skip_serializing_if = "Option::is_none")]
    value: Option<Option<f64>>,
}

/// The CiA 301 type name.
const fn type_name(ty: ParamType) -> &'static str {
    match ty {
        ParamType::Boolean => "BOOLEAN",
        ParamType::Unsigned8 => "UNSIGNED8",
        ParamType::Unsigned32 => "UNSIGNED32",
        ParamType::Real32 => "REAL32",
    }
}

/// `params [--config FILE] [--eds]`.
pub(crate) fn run(config: Option<&Path>, eds: bool) -> io::Result<()> {
    let config = config
        .map(Config::from_toml_file)
        .transpose()
        .map_err(io::Error::other)?;
    let mut out = io::stdout().lock();
    if eds {
        return out.write_all(eds_text().as_bytes());
    }
    for p in &PARAMS {
        let line = Line {
            name: p.name,
            index: p.index,
            sub: p.sub,
            ty: type_name(p.ty),
            unit: p.unit,
            low: p.low,
            high: p.high.is_finite().then_some(p.high),
            change: p.change.name(),
            doc: p.doc,
            value: config.map(|c| p.read(&c).ok().map(|raw| p.ty.to_f64(raw))),
        };
        serde_json::to_writer(&mut out, &line)?;
        writeln!(out)?;
    }
    Ok(())
}

/// The objects of [`PARAMS`], in order: (index, name, its parameters).
fn objects() -> Vec<(u16, &'static str, Vec<&'static Param>)> {
    let mut objects: Vec<(u16, &'static str, Vec<&'static Param>)> = Vec::new();
    for p in &PARAMS {
        match objects.last_mut() {
            Some((index, _, params)) if *index == p.index => params.push(p),
            _ => objects.push((p.index, object_name(p), vec![p])),
        }
    }
    objects
}

/// An object's name: its parameters' common prefix (`gains`, `odometry.pods[1]`).
fn object_name(p: &Param) -> &'static str {
    p.name.rsplit_once('.').map_or(p.name, |(head, _)| head)
}

/// The EDS (CiA 306, version 4.0) of the robot's object dictionary: identity, and one record
/// per object of [`PARAMS`], each entry with its type, access and limits.
pub(crate) fn eds_text() -> String {
    let objects = objects();
    let mut s = String::new();
    let w = &mut s;
    let _ = write!(
        w,
        "; mecanum_robot.eds: the mecanum robot's parameters as a CANopen object dictionary.\n\
         ; Written by `mecanum-codec params --eds` from firmware::params::PARAMS; do not edit.\n\
         ; The service, the classes and the object map: docs/protocol.md, section \"Parameters\".\n\
         \n[FileInfo]\nFileName=mecanum_robot.eds\nFileVersion=1\nFileRevision=0\nEDSVersion=4.0\n\
         Description=Mecanum drive robot: parameters (robot protocol version {PROTOCOL_VERSION})\n\
         CreatedBy=mecanum-drive\n\n[DeviceInfo]\nVendorName=mecanum-drive (no CiA vendor id)\n\
         VendorNumber=0x00000000\nProductName=Mecanum drive robot\nProductNumber=0x00000000\n\
         RevisionNumber=0x{PROTOCOL_VERSION:08X}\nOrderCode=mecanum-robot\n\
         BaudRate_125=1\nBaudRate_250=1\nBaudRate_500=1\nBaudRate_1000=1\n\
         SimpleBootUpMaster=0\nSimpleBootUpSlave=0\nGranularity=0\nDynamicChannelsSupported=0\n\
         GroupMessaging=0\nNrOfRXPDO=0\nNrOfTXPDO=0\nLSS_Supported=0\n\n\
         [Comments]\nLines=3\n\
         Line1=AccessType rw: live parameters change in any state, at the next control step;\n\
         Line2=the others (see each entry's Denotation) only while the robot is disabled.\n\
         Line3=ro: fixed at run time (a new configuration file or image changes them).\n\n\
         [MandatoryObjects]\nSupportedObjects=2\n1=0x1000\n2=0x1018\n\n\
         [OptionalObjects]\nSupportedObjects=2\n1=0x{STORE:04X}\n2=0x{RESTORE:04X}\n\n\
         [ManufacturerObjects]\nSupportedObjects={}\n",
        objects.len() + 1
    );
    for (i, (index, _, _)) in objects.iter().enumerate() {
        let _ = writeln!(w, "{}=0x{index:04X}", i + 1);
    }
    let _ = writeln!(w, "{}=0x{INFO_INDEX:04X}", objects.len() + 1);
    let _ = write!(
        w,
        "\n[1000]\nParameterName=Device type\nObjectType=0x7\nDataType=0x0007\nAccessType=ro\n\
         DefaultValue=0x00000000\nPDOMapping=0\n\n\
         [1018]\nParameterName=Identity object\nObjectType=0x9\nSubNumber=4\n\n\
         [1018sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\nDataType=0x0005\n\
         AccessType=const\nDefaultValue=3\nPDOMapping=0\n"
    );
    for (sub, name, value) in [
        (1, "Vendor-ID", 0),
        (2, "Product code", 0),
        (3, "Revision number", u32::from(PROTOCOL_VERSION)),
    ] {
        let _ = write!(
            w,
            "\n[1018sub{sub}]\nParameterName={name}\nObjectType=0x7\nDataType=0x0007\n\
             AccessType=ro\nDefaultValue=0x{value:08X}\nPDOMapping=0\n"
        );
    }
    for (index, name, signature) in [
        (STORE, "Store parameters", "save"),
        (RESTORE, "Restore default parameters", "load"),
    ] {
        let _ = write!(
            w,
            "\n[{index:04X}]\nParameterName={name}\nObjectType=0x8\nSubNumber=2\n\n\
             [{index:04X}sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\n\
             DataType=0x0005\nAccessType=ro\nDefaultValue=1\nPDOMapping=0\n\n\
             [{index:04X}sub1]\nParameterName=All parameters\nDenotation=write '{signature}'\n\
             ObjectType=0x7\nDataType=0x0007\nAccessType=rw\nDefaultValue=1\nPDOMapping=0\n"
        );
    }
    for (index, name, params) in &objects {
        let highest = firmware::params::highest_sub(*index).unwrap_or(0);
        let _ = write!(
            w,
            "\n[{index:04X}]\nParameterName={name}\nObjectType=0x9\nSubNumber={}\n\n\
             [{index:04X}sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\n\
             DataType=0x0005\nAccessType=const\nDefaultValue={highest}\nPDOMapping=0\n",
            params.len() + 1
        );
        for p in params {
            let access = if p.change == Change::Fixed {
                "ro"
            } else {
                "rw"
            };
            let _ = write!(
                w,
                "\n[{index:04X}sub{:X}]\nParameterName={}\nDenotation={} ({})\nObjectType=0x7\n\
                 DataType=0x{:04X}\nAccessType={access}\nLowLimit={}\n",
                p.sub,
                p.name,
                p.doc,
                p.change.name(),
                p.ty.data_type(),
                limit(p.low)
            );
            if p.high.is_finite() {
                let _ = writeln!(w, "HighLimit={}", limit(p.high));
            }
            let _ = writeln!(w, "PDOMapping=0");
        }
    }
    let _ = write!(
        w,
        "\n[{INFO_INDEX:04X}]\nParameterName=info\nObjectType=0x9\nSubNumber={}\n\n\
         [{INFO_INDEX:04X}sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\n\
         DataType=0x0005\nAccessType=const\nDefaultValue={}\nPDOMapping=0\n",
        INFO.len() + 1,
        INFO.len()
    );
    for (sub, (name, doc)) in (1..).zip(INFO) {
        let _ = write!(
            w,
            "\n[{INFO_INDEX:04X}sub{sub}]\nParameterName={name}\nDenotation={doc}\n\
             ObjectType=0x7\nDataType=0x0007\nAccessType=ro\nPDOMapping=0\n"
        );
    }
    s
}

/// A limit as the EDS writes it: a whole number without a fraction.
fn limit(v: f64) -> String {
    if v == v.trunc() && v.abs() < 1e15 {
        format!("{v:.0}")
    } else {
        format!("{v}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_eds_has_one_record_per_object_and_an_entry_per_parameter() {
        let eds = eds_text();
        // The records: the identity, one per object of PARAMS, and the info object; the save
        // and restore arrays.
        assert_eq!(eds.matches("ObjectType=0x9").count(), objects().len() + 2);
        assert_eq!(eds.matches("ObjectType=0x8").count(), 2);
        for p in &PARAMS {
            let entry = format!(
                "[{:04X}sub{:X}]\nParameterName={}\n",
                p.index, p.sub, p.name
            );
            assert!(eds.contains(&entry), "{}", p.name);
        }
        // `inf` is a setting of the stop decelerations: no HighLimit there.
        let stop = eds
            .split("ParameterName=limits.stop_linear_decel")
            .nth(1)
            .unwrap();
        assert!(!stop.split("\n\n").next().unwrap().contains("HighLimit"));
    }
}
