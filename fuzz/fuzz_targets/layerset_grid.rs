//! Any bytes given to the reader of a mesh layer's grid file (layer-set manifest version 3),
//! for a small and a large camera: an error or a checked grid, never a panic; a grid that
//! decodes encodes to a file that decodes to the same grid.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for (w, h) in [(37, 21), (1920, 1080)] {
        if let Ok(g) = cpsl_io::grid::decode_grid(data, w, h) {
            let again = cpsl_io::grid::decode_grid(&cpsl_io::grid::encode_grid(&g), w, h);
            assert_eq!(again.expect("re-decodes"), g);
        }
    }
});
