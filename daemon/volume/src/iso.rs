//! The one rule for an iso value against a volume's data, for every place an iso enters (the
//! render command, a wall config's `[volume] iso`, the operator console's `/api/render`): it must
//! be a finite number within the data's value range `[lo, hi]` (inclusive). Above the range no
//! voxel reaches the iso and every ray misses (an empty image); below it the whole box is inside
//! the surface (a solid box).

/// Why an iso value does not fit a volume. `Display` names the value and the range, not the field:
/// the caller says where the value came from (`--iso`, `[volume] iso`, `render: \`iso\``).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum IsoError {
    #[error("{iso} is not a finite number")]
    NotFinite { iso: f64 },
    #[error(
        "{iso} is outside the volume's value range [{lo}, {hi}]: {}",
        if iso > hi { "no voxel reaches it, so every ray would miss (an empty image)" }
        else { "every voxel is above it, so the whole box would be inside (a solid box)" }
    )]
    OutOfRange { iso: f64, lo: f64, hi: f64 },
}

/// Checks `iso` against the data's value range `(lo, hi)`, in the data's units.
pub fn check_iso(iso: f64, (lo, hi): (f64, f64)) -> Result<(), IsoError> {
    if !iso.is_finite() {
        return Err(IsoError::NotFinite { iso });
    }
    if iso < lo || iso > hi {
        return Err(IsoError::OutOfRange { iso, lo, hi });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_iso_within_the_range_ends_included_is_accepted() {
        for iso in [-2.0, 0.0, 3.5] {
            assert_eq!(check_iso(iso, (-2.0, 3.5)), Ok(()), "{iso}");
        }
    }

    #[test]
    fn an_iso_outside_the_range_is_refused_naming_the_range_and_what_it_would_render() {
        let above = check_iso(5000.0, (-1024.0, 3071.0)).unwrap_err().to_string();
        assert_eq!(
            above,
            "5000 is outside the volume's value range [-1024, 3071]: no voxel reaches it, so every ray \
             would miss (an empty image)"
        );
        let below = check_iso(-50.0, (0.0, 255.0)).unwrap_err().to_string();
        assert!(below.starts_with("-50 is outside the volume's value range [0, 255]: "), "{below}");
        assert!(below.contains("solid box"), "{below}");
    }

    #[test]
    fn a_non_finite_iso_is_refused() {
        for iso in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let e = check_iso(iso, (0.0, 1.0)).unwrap_err();
            assert!(matches!(e, IsoError::NotFinite { .. }), "{iso}: {e}");
        }
    }
}
