//! The date reports were made (they are written with `cpsl_io::write_json`).

pub use cpsl_core::run::today;
