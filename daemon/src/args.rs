//! Small value parsers shared by the subcommands' flags.

use glam::DVec3;

/// `X,Y,Z` as three finite numbers.
pub fn vec3(s: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|_| format!("'{p}' is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(DVec3::new(x, y, z)),
        [_, _, _] => Err("values must be finite".into()),
        _ => Err(format!("expected X,Y,Z (three numbers), got {} value(s)", v.len())),
    }
}

/// `WxH` image size, each 1..=16384.
pub fn size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH, e.g. 512x512, got '{s}'"))?;
    let p = |t: &str| t.trim().parse::<u32>().map_err(|_| format!("'{t}' is not a whole number"));
    let (w, h) = (p(w)?, p(h)?);
    if !(1..=16384).contains(&w) || !(1..=16384).contains(&h) {
        return Err(format!("{w}x{h}: each side must be 1..=16384"));
    }
    Ok((w, h))
}

/// `NX,NY,NZ` raw-volume dimensions.
pub fn dims(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| p.trim().parse::<usize>().map_err(|_| format!("'{p}' is not a whole number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z] if x > 0 && y > 0 && z > 0 => Ok([x, y, z]),
        [_, _, _] => Err("dimensions must be at least 1".into()),
        _ => Err(format!("expected NX,NY,NZ, got {} value(s)", v.len())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses() {
        assert_eq!(vec3("1, 2.5,-3").unwrap(), DVec3::new(1.0, 2.5, -3.0));
        assert!(vec3("1,2").unwrap_err().contains("three"));
        assert!(vec3("1,a,2").unwrap_err().contains("'a'"));
        assert!(vec3("1,inf,2").is_err());
        assert_eq!(size("640x480").unwrap(), (640, 480));
        assert!(size("640").is_err());
        assert!(size("0x10").is_err());
        assert_eq!(dims("256,256,108").unwrap(), [256, 256, 108]);
        assert!(dims("2,0,2").is_err());
    }
}
