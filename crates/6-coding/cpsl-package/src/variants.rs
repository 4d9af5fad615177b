//! Variant sets (`variants.json`): packages of the same content at several bitrates, which a
//! player switches between at segment boundaries.

use crate::PackageError;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// File naming the bitrate variants of one piece of content.
pub const VARIANTS_FILE: &str = "variants.json";
/// Format name of a variant set.
pub const VARIANTS_FORMAT: &str = "cpsl-variants";

/// A variant set: packages of the same content at several bitrates (`variants.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantSet {
    /// Always [`VARIANTS_FORMAT`].
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// Package folders relative to the set's file, cheapest first.
    pub variants: Vec<String>,
}

impl VariantSet {
    /// A set of the package folders `variants` (cheapest first).
    pub fn new(variants: Vec<String>) -> Self {
        Self {
            format: VARIANTS_FORMAT.into(),
            version: 1,
            variants,
        }
    }

    /// Writes the set as `dir/variants.json`, atomically.
    pub fn write(&self, dir: &Path) -> Result<(), PackageError> {
        let json = serde_json::to_string_pretty(self).expect("a variant set serialises") + "\n";
        cpsl_io::write_file_atomic(&dir.join(VARIANTS_FILE), json.as_bytes())?;
        Ok(())
    }
}
