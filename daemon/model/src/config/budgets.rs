//! The budgets of a volume read through the brick cache (DESIGN.md "Large volumes"): the one rule
//! for `[volume] gpu_budget_mb`, `host_budget_mb` and `upload_mb_per_frame` and for the flags
//! of the same names (`isowalld render --gpu-budget-mb`, `isowalld bench stream`).

/// Largest GPU or host budget: 1 TiB, in MiB.
pub const MAX_BUDGET_MB: u64 = 1 << 20;

/// What a node's brick cache may hold, in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BrickBudgets {
    /// The GPU pool: its bricks, page tables and block levels.
    pub gpu: u64,
    /// Decoded bricks held in memory (a brick evicted from the pool is read again from here,
    /// not from the store).
    pub host: u64,
    /// The most bytes uploaded to the pool in one frame, so that moving frames keep their rate.
    pub upload_per_frame: u64,
}

/// A budget outside its range: which one (the config key: `gpu_budget_mb`, `host_budget_mb`,
/// `upload_mb_per_frame`; a flag is the same name with dashes) and what is wrong with its value.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{field} {problem}")]
pub struct BudgetError {
    pub field: &'static str,
    pub problem: String,
}

impl BrickBudgets {
    /// From MiB: the host budget defaults to twice the GPU's, the uploads a frame to a sixteenth
    /// of the GPU's (a still view's set of a few hundred bricks refines in about 16 frames). The
    /// caller says where the value came from (a config key or a flag).
    pub fn from_mb(
        gpu_mb: u64,
        host_mb: Option<u64>,
        upload_mb: Option<f64>,
    ) -> Result<BrickBudgets, BudgetError> {
        let bytes = |v: u64, field: &'static str| {
            if (1..=MAX_BUDGET_MB).contains(&v) {
                Ok(v << 20)
            } else {
                Err(BudgetError { field, problem: format!("{v} is outside 1..={MAX_BUDGET_MB} (MiB)") })
            }
        };
        let gpu = bytes(gpu_mb, "gpu_budget_mb")?;
        let host = bytes(host_mb.unwrap_or(gpu_mb.saturating_mul(2).min(MAX_BUDGET_MB)), "host_budget_mb")?;
        let upload_per_frame = match upload_mb {
            None => gpu / 16,
            Some(mb) if mb.is_finite() && mb > 0.0 && mb <= MAX_BUDGET_MB as f64 => (mb * 1048576.0) as u64,
            Some(mb) => {
                let problem = format!("{mb} is outside (0, {MAX_BUDGET_MB}] (MiB)");
                return Err(BudgetError { field: "upload_mb_per_frame", problem });
            }
        };
        Ok(BrickBudgets { gpu, host, upload_per_frame: upload_per_frame.max(1) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_the_gpu_budget_and_bad_values_name_their_field() {
        let b = BrickBudgets::from_mb(64, None, None).unwrap();
        assert_eq!((b.gpu, b.host, b.upload_per_frame), (64 << 20, 128 << 20, 4 << 20));
        let b = BrickBudgets::from_mb(64, Some(8), Some(0.5)).unwrap();
        assert_eq!((b.host, b.upload_per_frame), (8 << 20, 512 << 10));
        assert!(BrickBudgets::from_mb(0, None, None).unwrap_err().to_string().contains("gpu_budget_mb 0"));
        assert!(BrickBudgets::from_mb(1, Some(0), None)
            .unwrap_err()
            .to_string()
            .contains("host_budget_mb 0"));
        assert!(BrickBudgets::from_mb(MAX_BUDGET_MB + 1, None, None).is_err());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(BrickBudgets::from_mb(1, None, Some(bad))
                .unwrap_err()
                .to_string()
                .contains("upload_mb_per_frame"));
        }
    }
}
