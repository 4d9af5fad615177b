//! Evaluation of CPSL renders: metrics and real datasets with ground truth.

pub mod datasets;
pub mod metrics;
