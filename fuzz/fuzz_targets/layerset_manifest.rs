//! Any bytes given to the layer-set manifest reader (versions 1 to 3, with layer geometry and grid files):
//! an error or a checked manifest, never a panic; a manifest that parses re-serialises to one
//! that parses to the same value.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = cpsl_core::Manifest::parse(data) {
        let again = cpsl_core::Manifest::parse(m.to_json().as_bytes()).expect("re-parses");
        assert_eq!(again.layers.len(), m.layers.len());
        for (a, b) in again.layers.iter().zip(&m.layers) {
            assert_eq!(a.file, b.file);
            assert_eq!(a.geometry.is_plane(), b.geometry.is_plane());
            assert_eq!(a.grid, b.grid);
        }
    }
});
