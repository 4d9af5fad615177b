//! Evaluation of CPSL renders.

pub mod metrics;
