//! The layouts against ROS 2's, the schemas' dependency sections, and frame round trips.

use super::*;

#[test]
fn a_frame_is_the_ros2_socketcan_layout() {
    let f = Frame {
        header: Header::new(1_000_000_002, "ab"),
        id: 0x201,
        is_rtr: false,
        is_extended: true,
        is_error: false,
        dlc: 8,
        data: [1, 2, 3, 4, 5, 6, 7, 8],
    };
    let mut out = Vec::new();
    encode(&mut out, &f);
    #[rustfmt::skip]
    let want = [
        0, 1, 0, 0, // encapsulation
        1, 0, 0, 0, 2, 0, 0, 0, // stamp 1 s 2 ns
        3, 0, 0, 0, b'a', b'b', 0, // "ab" with its NUL, length 3
        0, // padding to 4
        1, 2, 0, 0, // id
        0, 1, 0, 8, // is_rtr, is_extended, is_error, dlc
        1, 2, 3, 4, 5, 6, 7, 8,
    ];
    assert_eq!(out, want);
    assert_eq!(decode::<Frame>(&out).unwrap(), f);
}

#[test]
fn odometry_aligns_its_doubles_from_the_payload_start() {
    let o = Odometry {
        header: Header::new(5, "odom"),
        child_frame_id: "base_link".into(),
        pose: PoseWithCovariance {
            pose: Pose::planar([1.0, 2.0, 0.5]),
            covariance: [0.25; 36],
        },
        twist: TwistWithCovariance {
            twist: Twist::planar([0.1, 0.2, 0.3]),
            covariance: [0.0; 36],
        },
    };
    let mut out = Vec::new();
    encode(&mut out, &o);
    // Header: 8 + 4 + "odom\0" = 17 -> 20 (align 4); child: 4 + "base_link\0" = 34 -> 40
    // (align 8) for x.
    let x = f64::from_le_bytes(out[4 + 40..4 + 48].try_into().unwrap());
    assert_eq!(x, 1.0);
    // 7 doubles of pose and 36 of covariance, 6 of twist and 36 of covariance.
    assert_eq!(out.len(), 4 + 40 + 8 * (7 + 36 + 6 + 36));
    let back = decode::<Odometry>(&out).unwrap();
    assert_eq!(back, o);
    let p = back.pose.pose.to_planar();
    assert!((p[2] - 0.5).abs() < 1e-15, "{p:?}");
}

/// A tracker's pose, as a ROS 2 publisher writes it (built by hand here, not by
/// [`encode`]): the doubles start at the next multiple of 8 after the frame id.
#[test]
fn a_tracker_pose_stamped_decodes_from_the_ros2_layout() {
    let mut raw = vec![0, 1, 0, 0];
    raw.extend_from_slice(&3i32.to_le_bytes()); // stamp 3 s
    raw.extend_from_slice(&500u32.to_le_bytes()); // 500 ns
    raw.extend_from_slice(&6u32.to_le_bytes()); // "world" and its NUL
    raw.extend_from_slice(b"world\0");
    raw.extend_from_slice(&[0; 6]); // 18 -> 24, the alignment of a double
    let yaw: f64 = -2.5;
    for v in [
        1.25,
        -0.5,
        0.0,
        0.0,
        0.0,
        (yaw / 2.0).sin(),
        (yaw / 2.0).cos(),
    ] {
        raw.extend_from_slice(&f64::to_le_bytes(v));
    }
    let p = decode::<PoseStamped>(&raw).unwrap();
    assert_eq!(p.header, Header::new(3_000_000_500, "world"));
    let planar = p.pose.to_planar();
    assert_eq!(planar[..2], [1.25, -0.5]);
    assert!((planar[2] - yaw).abs() < 1e-15, "{planar:?}");
    let mut out = Vec::new();
    encode(&mut out, &p);
    assert_eq!(out, raw);
    assert!(
        POSE_STAMPED
            .schema_text()
            .contains("\nMSG: geometry_msgs/Quaternion\n")
    );
}

#[test]
fn a_schema_lists_each_dependency_once_after_its_separator() {
    let text = ODOMETRY.schema_text();
    assert!(text.starts_with("std_msgs/Header header\n"));
    for dep in [
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose",
        "geometry_msgs/Point",
        "geometry_msgs/Quaternion",
        "geometry_msgs/TwistWithCovariance",
        "geometry_msgs/Twist",
        "geometry_msgs/Vector3",
    ] {
        let section = format!("{}\nMSG: {dep}\n", "=".repeat(80));
        assert_eq!(text.matches(&section).count(), 1, "{dep}:\n{text}");
    }
    assert_eq!(text.matches("\nMSG: ").count(), 9);
}

#[test]
fn every_can_frame_round_trips() {
    use embedded_can::{ExtendedId, Frame as _, StandardId};
    let frames = [
        firmware::CanFrame::new(StandardId::new(0x7FF).unwrap(), &[9; 3]).unwrap(),
        firmware::CanFrame::new(ExtendedId::new(0x1ABC_DEF0).unwrap(), &[]).unwrap(),
        firmware::CanFrame::new_remote(StandardId::new(0x29).unwrap(), 8).unwrap(),
        firmware::CanFrame::new_remote(ExtendedId::new(0x1).unwrap(), 4).unwrap(),
    ];
    for f in frames {
        let m = Frame::from_can(7, &f);
        let mut out = Vec::new();
        encode(&mut out, &m);
        assert_eq!(decode::<Frame>(&out).unwrap().to_can(), Some(f), "{f:?}");
    }
    let bad = Frame {
        id: 0x800,
        ..Frame::default()
    };
    assert_eq!(bad.to_can(), None);
    assert!(matches!(
        decode::<Frame>(&[0, 0, 0, 0, 1]),
        Err(DecodeError::Encapsulation { .. })
    ));
    assert!(matches!(
        decode::<Frame>(&[0, 1, 0, 0, 1]),
        Err(DecodeError::Payload { .. })
    ));
}

proptest::proptest! {
    /// The log's own layout of a frame is serde's, byte for byte: every id kind, remote or
    /// not, every length, stamps past the 32-bit seconds.
    #[test]
    fn a_frame_laid_out_by_hand_is_the_serde_encoding(
        raw in 0u32..(1 << 29),
        extended: bool,
        remote: bool,
        data in proptest::collection::vec(proptest::num::u8::ANY, 0..=8),
        stamp_ns: u64,
    ) {
        use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
        let id: Id = if extended {
            ExtendedId::new(raw).unwrap().into()
        } else {
            StandardId::new((raw & 0x7FF) as u16).unwrap().into()
        };
        let frame = if remote {
            firmware::CanFrame::new_remote(id, data.len())
        } else {
            firmware::CanFrame::new(id, &data)
        }
        .unwrap();
        let mut serde = vec![7];
        encode(&mut serde, &Frame::from_can(stamp_ns, &frame));
        let mut by_hand = vec![7];
        Frame::encode_can(&mut by_hand, stamp_ns, &frame);
        proptest::prop_assert_eq!(by_hand, serde);
    }
}
