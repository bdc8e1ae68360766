//! What runs and logs say: summaries, plots, calibration, sweeps, the bring-up check.
//!
//! A log's summary and plot, calibration fitted from a log, sweeps of many runs, the bring-up
//! check's verdict on a robot's wiring, and a kinematics calculator.

pub mod bringup;
pub mod calibrate;
pub mod kin;
pub mod plot;
pub mod summary;
pub mod sweep;
