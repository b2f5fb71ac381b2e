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

pub use isowall_model::cli_args::size;

/// What a raw volume (a file with no header) needs said: `--dims`, `--type`, `--spacing`; the
/// same options for every command that reads a volume.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct RawVolumeArgs {
    /// Raw volumes: dimensions
    #[arg(long, value_name = "NX,NY,NZ", value_parser = dims)]
    pub dims: Option<[usize; 3]>,
    /// Raw volumes: voxel type (uint8, int8, uint16, int16, uint32, int32, float32, float64),
    /// little endian
    #[arg(long = "type", value_name = "TYPE")]
    pub voxel_type: Option<isowall_volume::io::VoxelType>,
    /// Raw volumes: voxel spacing [default: 1,1,1]
    #[arg(long, value_name = "SX,SY,SZ", value_parser = vec3)]
    pub spacing: Option<DVec3>,
}

impl RawVolumeArgs {
    /// The raw layout (`None` for a file that says its own): both `--dims` and `--type`, or
    /// neither.
    pub fn spec(&self) -> anyhow::Result<Option<isowall_volume::io::RawSpec>> {
        match (self.dims, self.voxel_type) {
            (None, None) if self.spacing.is_none() => Ok(None),
            (Some(dims), Some(voxel)) => Ok(Some(isowall_volume::io::RawSpec {
                dims,
                voxel,
                spacing: self.spacing.unwrap_or(DVec3::ONE),
                big_endian: false,
                header_bytes: 0,
            })),
            _ => anyhow::bail!("a raw volume needs both --dims and --type (and optionally --spacing)"),
        }
    }
}

/// How a command that reads one volume whole reads it (`info`, `convert`): the DICOM series, the
/// time step, a raw file's layout and the size limit.
#[derive(clap::Args, Clone, Debug)]
pub struct VolumeInputArgs {
    /// DICOM: the SeriesInstanceUID where the folder holds several
    #[arg(long, value_name = "UID")]
    pub series: Option<String>,
    /// Time-varying volumes: the time step, from 0
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub step: usize,
    #[command(flatten)]
    pub raw: RawVolumeArgs,
    /// The most bytes the volume may take as float32 (4 a voxel), checked from its header before
    /// it is read [default: 2 GiB]
    #[arg(long, value_name = "BYTES")]
    pub max_volume_bytes: Option<u64>,
}

impl VolumeInputArgs {
    /// The source `volume` names (as given on the command line), its series chosen, and a raw
    /// file's layout.
    pub fn source(
        &self,
        volume: &str,
    ) -> anyhow::Result<(isowall_volume::VolumeSource, Option<isowall_volume::io::RawSpec>)> {
        let source: isowall_volume::VolumeSource = volume.parse()?;
        Ok((source.with_series(self.series.as_deref())?, self.raw.spec()?))
    }

    /// The size limit of what is read whole (`--max-volume-bytes`).
    pub fn limit(&self) -> isowall_volume::io::VolumeLimit {
        match self.max_volume_bytes {
            Some(b) => isowall_volume::io::VolumeLimit::new(b, "--max-volume-bytes"),
            None => isowall_volume::io::VolumeLimit::default(),
        }
    }

    /// Reads `volume` (a source as given on the command line) whole, with a spinner meanwhile.
    pub fn read(
        &self,
        volume: &str,
    ) -> anyhow::Result<(isowall_volume::VolumeSource, isowall_volume::Volume)> {
        use anyhow::Context;
        let (source, raw) = self.source(volume)?;
        let limit = self.limit();
        let bar = crate::progress::spinner(format!("reading {source}"));
        let read = source.load_step_within(raw.as_ref(), self.step, &limit);
        bar.finish_and_clear();
        let volume = read.with_context(|| format!("cannot read {source}"))?;
        Ok((source, volume))
    }
}

/// Frames accumulated into one picture (a bench's reference, the look's frames): 1..= the
/// renderer's most, as `render --frames`.
pub fn accumulated_frames(s: &str) -> Result<u32, String> {
    isowall_model::cli_args::whole_within(s, 1, isowall_render::gpu::MAX_FRAMES, "frames")
}

/// Repeats of a measurement as a `u32` ([`isowall_model::cli_args::repeats`]'s range).
pub fn repeats_u32(s: &str) -> Result<u32, String> {
    isowall_model::cli_args::repeats(s).map(|n| n as u32)
}

/// Surface pixels sampled by a bench's independent truth: 1..=100000 (each is traced by the
/// brute-force estimator).
pub fn truth_pixels(s: &str) -> Result<usize, String> {
    isowall_model::cli_args::whole_within(s, 1, 100_000, "pixels")
}

/// Directions per truth pixel of the brute-force estimator: 1..=4096.
pub fn truth_directions(s: &str) -> Result<u32, String> {
    isowall_model::cli_args::whole_within(s, 1, 4096, "directions")
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
