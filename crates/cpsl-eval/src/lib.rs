//! Evaluation of CPSL renders: metrics and real datasets with ground truth.

pub mod baselines;
pub mod datasets;
pub mod metrics;
