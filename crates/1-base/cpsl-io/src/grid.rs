//! A mesh layer's depth grid as a side file of its layer set (`layer_NN.grid`, layer-set
//! manifest version 3): exact, and an eighteenth of the size of the same grid as JSON numbers.
//!
//! Little endian: a 24-byte header (magic `CPSLGRD\0`, `u16` version 1, `u16` flags 0,
//! `u32` step, `u32` vertex columns, `u32` vertex rows) followed by a zlib stream of the
//! `cols * rows` inverse depths (`f32`, row by row) stored as four byte planes, every value's
//! lowest byte first, then every value's second byte, and so on: neighbouring vertices share
//! their sign, exponent and leading mantissa bits, so the high planes compress to little.
//! Readers check the header against the layer set's camera before inflating anything
//! ([`decode_grid`]), then the values ([`DepthGrid::check`]).

use cpsl_core::DepthGrid;
use std::io::{Read, Write};

/// The file's first eight bytes.
pub const GRID_MAGIC: &[u8; 8] = b"CPSLGRD\0";
/// The version written.
pub const GRID_VERSION: u16 = 1;
const HEADER: usize = 24;

/// The side file of `grid`.
pub fn encode_grid(grid: &DepthGrid) -> Vec<u8> {
    let n = grid.inverse_depth.len();
    let mut planes = vec![0u8; 4 * n];
    for (i, v) in grid.inverse_depth.iter().enumerate() {
        for (b, byte) in v.to_le_bytes().into_iter().enumerate() {
            planes[b * n + i] = byte;
        }
    }
    let mut out = Vec::with_capacity(HEADER + n);
    out.extend_from_slice(GRID_MAGIC);
    out.extend_from_slice(&GRID_VERSION.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    for v in [grid.step, grid.cols, grid.rows] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let mut z = flate2::write::ZlibEncoder::new(out, flate2::Compression::fast());
    z.write_all(&planes).expect("writing to memory");
    z.finish().expect("writing to memory")
}

/// Reads a grid side file for a `width x height` layer set: the header must give the grid
/// [`DepthGrid::dims`] prescribes for its step, the stream exactly its values, and every value
/// must be finite and above zero. The error says what is wrong.
pub fn decode_grid(bytes: &[u8], width: u32, height: u32) -> Result<DepthGrid, String> {
    if bytes.len() < HEADER || &bytes[..8] != GRID_MAGIC {
        return Err("not a grid file (magic CPSLGRD)".into());
    }
    let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
    match (u16_at(8), u16_at(10)) {
        (GRID_VERSION, 0) => {}
        (GRID_VERSION, flags) => return Err(format!("unknown flags {flags:#06x}")),
        (v, _) => return Err(format!("version {v}, this build reads {GRID_VERSION}")),
    }
    let (step, cols, rows) = (u32_at(12), u32_at(16), u32_at(20));
    // The size is checked before anything is allocated.
    let mut grid = DepthGrid {
        step,
        cols,
        rows,
        inverse_depth: Vec::new(),
    };
    let (c, r) = if (1..=DepthGrid::MAX_STEP).contains(&step) {
        DepthGrid::dims(width, height, step)
    } else {
        (0, 0)
    };
    if (cols, rows) != (c, r) {
        // Reported by the grid's own check.
        return Err(grid.check(width, height).err().map_or_else(
            || "vertex count does not fit the camera".into(),
            |e| e.to_string(),
        ));
    }
    let n = (cols * rows) as usize;
    let mut planes = vec![0u8; 4 * n];
    let mut z = flate2::read::ZlibDecoder::new(&bytes[HEADER..]);
    z.read_exact(&mut planes)
        .map_err(|e| format!("values: {e} (expected {n} values)"))?;
    let mut rest = [0u8; 1];
    if !matches!(z.read(&mut rest), Ok(0)) || z.total_in() as usize != bytes.len() - HEADER {
        return Err(format!("data after the {n} values"));
    }
    grid.inverse_depth = (0..n)
        .map(|i| {
            f32::from_le_bytes([
                planes[i],
                planes[n + i],
                planes[2 * n + i],
                planes[3 * n + i],
            ])
        })
        .collect();
    grid.check(width, height).map_err(|e| e.to_string())?;
    Ok(grid)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> DepthGrid {
        let (cols, rows) = DepthGrid::dims(10, 7, 4);
        DepthGrid {
            step: 4,
            cols,
            rows,
            inverse_depth: (0..cols * rows).map(|i| 0.25 + i as f32 * 1e-3).collect(),
        }
    }

    #[test]
    fn roundtrip_is_exact() {
        let g = grid();
        let bytes = encode_grid(&g);
        assert_eq!(decode_grid(&bytes, 10, 7).unwrap(), g);
    }

    #[test]
    fn rejects_what_does_not_fit() {
        let bytes = encode_grid(&grid());
        // Another camera.
        let e = decode_grid(&bytes, 14, 7).unwrap_err();
        assert!(e.contains("needs 5x3"), "{e}");
        // Magic, version, flags.
        assert!(decode_grid(&bytes[..10], 10, 7)
            .unwrap_err()
            .contains("magic"));
        let mut b = bytes.clone();
        b[8] = 9;
        assert!(decode_grid(&b, 10, 7).unwrap_err().contains("version 9"));
        let mut b = bytes.clone();
        b[10] = 1;
        assert!(decode_grid(&b, 10, 7).unwrap_err().contains("flags"));
        // Step out of range.
        let mut b = bytes.clone();
        b[12..16].copy_from_slice(&0u32.to_le_bytes());
        assert!(decode_grid(&b, 10, 7).unwrap_err().contains("step 0"));
        // A stream cut short, or with more after it.
        let e = decode_grid(&bytes[..bytes.len() - 3], 10, 7).unwrap_err();
        assert!(e.contains("values"), "{e}");
        let mut b = bytes.clone();
        b.push(0);
        assert!(decode_grid(&b, 10, 7).unwrap_err().contains("after"));
        // A value that is not a depth.
        let mut g = grid();
        g.inverse_depth[5] = f32::NAN;
        let e = decode_grid(&encode_grid(&g), 10, 7).unwrap_err();
        assert!(e.contains("vertex (1, 1)"), "{e}");
        g.inverse_depth[5] = -1.0;
        assert!(decode_grid(&encode_grid(&g), 10, 7).is_err());
    }

    proptest::proptest! {
        /// Corrupted files never panic.
        #[test]
        fn never_panics(pos in 0usize..200, val in proptest::prelude::any::<u8>(), cut in 0usize..200) {
            let mut b = encode_grid(&grid());
            let i = pos % b.len();
            b[i] = val;
            let _ = decode_grid(&b, 10, 7);
            b.truncate(cut % (b.len() + 1));
            let _ = decode_grid(&b, 10, 7);
        }
    }
}
