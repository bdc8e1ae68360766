use std::ops::ControlFlow;

use embedded_can::StandardId;
use firmware::CanFrame;

use super::core::pose_array;
use super::*;
use crate::bus::{Fault, FaultKind, frame_bits};
use crate::engine::{run_observed, run_until};
use crate::nodes::test_plant::Moving;

fn id_of(frame: &CanFrame) -> u16 {
    match embedded_can::Frame::id(frame) {
        embedded_can::Id::Standard(id) => id.as_raw(),
        embedded_can::Id::Extended(_) => 0,
    }
}

#[test]
fn an_observer_can_end_the_run_after_any_step() {
    let s = Scenario::load("square", None).unwrap();
    let mut plant = super::plant_for(&s).unwrap();
    let mut last = 0;
    let summary = run_until(&s, &mut plant, None, LogOptions::default(), |step| {
        last = step.t_us;
        if step.t_us >= 500_000 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })
    .unwrap();
    assert_eq!(last, 500_000);
    assert_eq!(summary.steps, 501);
    assert!(
        (summary.duration_s - 0.5).abs() < 1e-12,
        "{}",
        summary.duration_s
    );
    // The same steps as a whole run's first half second.
    let mut whole = Vec::new();
    let mut plant = super::plant_for(&s).unwrap();
    run_observed(&s, &mut plant, None, LogOptions::default(), |step| {
        if step.t_us <= 500_000 {
            whole.push(step.controller.pose());
        }
    })
    .unwrap();
    assert_eq!(summary.odometry, pose_array(whole[500]));
}

#[test]
fn frames_for_the_drives_act_at_their_delivery_even_at_the_same_instant() {
    let frame = |id| CanFrame::standard(StandardId::new(id).unwrap(), &[0; 8]).unwrap();
    let (a, b) = (frame(0x200), frame(0x300));
    // 0x200 wins arbitration and ends first; delayed by the length of 0x300, it reaches
    // the drives at the very instant 0x300 does.
    let delay_us = u64::from(frame_bits(&b));
    let scenario = Scenario::load("square", None).unwrap();
    let mut engine = Engine::new(
        &scenario,
        Moving::new([0.0; 3]),
        None,
        LogOptions::default(),
    );
    engine.bus = Bus::new(
        1_000_000,
        vec![Fault {
            kind: FaultKind::Delay { micros: delay_us },
            from_us: 0,
            until_us: 1_000,
            sender: Some(Node::Controller),
        }],
        1,
    );
    engine.bus.send(0, Node::Controller, a);
    engine.bus.send(0, Node::Host, b);
    let mut core = InProcess::new(&scenario, LogOptions::default()).unwrap();
    engine.advance_period(&mut core, 0).unwrap();
    let at = u64::from(frame_bits(&a) + frame_bits(&b)) * 1000;
    let applied: Vec<_> = engine
        .plant
        .frames
        .iter()
        .map(|(t, f)| (*t, id_of(f)))
        .collect();
    assert_eq!(applied, [(at, 0x200), (at, 0x300)]);
    assert_eq!(engine.plant.now_ns, 1_000_000);
    // Both reached the receivers, for the firmware's side at the next tick.
    assert_eq!(engine.delivered.len(), 2);
}
