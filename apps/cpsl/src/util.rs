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
