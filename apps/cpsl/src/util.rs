//! Small helpers shared by the commands.

/// Parses `R,G,B` (0-255 each).
pub fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let v: Vec<u8> = s
        .split(',')
        .map(|p| p.trim().parse::<u8>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("colour '{s}': {e}; expected R,G,B with values 0-255"))?;
    <[u8; 3]>::try_from(v)
        .map_err(|v| format!("colour '{s}': expected 3 values, found {}", v.len()))
}

/// Says on stderr that `damaged` packets of `input` were skipped, if any.
pub fn warn_damaged(input: &std::path::Path, damaged: usize) {
    if damaged > 0 {
        eprintln!(
            "warning: {}: {damaged} damaged packet(s) skipped; their frames are missing",
            input.display()
        );
    }
}
