//! Evaluation of CPSL renders: metrics, coverage (hole and crack ratios), baselines and real
//! datasets with ground truth.

pub mod baselines;
pub mod coverage;
pub mod datasets;
pub mod metrics;
pub mod temporal;
