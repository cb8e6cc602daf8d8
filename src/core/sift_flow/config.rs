//! The parameters of SIFT flow (Ce Liu's reference defaults, the `fast` preset) and their one
//! validation, so that the hot path never checks them again.

use serde::{Deserialize, Serialize};

use super::FlowError;

/// Largest number of labels per layer (search window side) the fixed-size buffers allow.
pub(super) const MAX_LABELS: usize = 64;

/// How the integer flow of the finest level is refined below a pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SubpixelRefinement {
    /// Integer flow, as the reference.
    None,
    /// Parabola through the matching cost at the chosen label and its two neighbours, per axis.
    DataCostParabola,
    /// Parabola through the final belief (data + smoothness messages) of each layer.
    BeliefParabola,
}

/// Which implementation computes the L1 distance of two 128-byte descriptors. `Auto` picks the
/// fastest the CPU has; the others exist to measure the difference.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum L1Kernel {
    Auto,
    /// Plain Rust loop over bytes.
    Portable,
    /// x86-64 `psadbw` on 16-byte lanes (baseline on every x86-64 CPU).
    Sse2,
    /// x86-64 AVX2 `vpsadbw` on 32-byte lanes (falls back to `Sse2` when absent).
    Avx2,
}

/// Parameters of coarse-to-fine SIFT flow. Defaults are Ce Liu's reference (`SIFTflowc2f` demo):
/// costs are in units of summed absolute byte differences of the 128-byte descriptors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SiftFlowConfig {
    /// Pyramid levels including full resolution. Reference: 4.
    pub pyramid_levels: usize,
    /// Search half-window at the coarsest level, px of that level (21×21 candidates). Reference: 10.
    pub top_search_radius_px: usize,
    /// Search half-window around the propagated flow at the finest level, px; level `i` (0 = finest)
    /// uses `search_radius_px + i`. Reference: 2.
    pub search_radius_px: usize,
    /// Belief-propagation iterations at the coarsest level. Reference: 60.
    pub top_iterations: usize,
    /// Belief-propagation iterations at every other level. Reference: 30.
    pub iterations: usize,
    /// α: smoothness cost per px of flow difference between 4-neighbours. Reference: 2·255.
    pub smoothness_weight: f32,
    /// d: truncation of the smoothness cost. Reference: 40·255.
    pub smoothness_truncation: f32,
    /// γ: cost per px of flow magnitude (|u| + |v|) at full resolution, doubled per coarser level.
    /// Reference: 0.005·255.
    pub flow_magnitude_weight: f32,
    /// Truncate matching costs at their median (the reference's `IsDataTermTruncated`, off there).
    pub truncate_data_cost: bool,
    /// σ of the 5-tap Gaussian applied before each 2× downsampling of the descriptors, px.
    /// Reference: 0.67.
    pub pyramid_sigma_px: f32,
    /// Sub-pixel refinement of the finest level's integer flow. Default: `DataCostParabola` (our
    /// addition; the reference's flow is integer): on the 505×275 shared pair it lowers the
    /// end-point error from 0.445 px (integer, as the reference's 0.440) to 0.277 px.
    pub subpixel: SubpixelRefinement,
    /// Implementation of the descriptor L1 distance (results are identical).
    pub l1_kernel: L1Kernel,
    /// Multigrid belief propagation as the reference (`nHierarchy`): before each pyramid level's
    /// iterations, solve the same problem on 2×2, 4×4, … blocks (depth 2 at the top, `levels − 1 −
    /// level` below) and start from their messages.
    pub multigrid: bool,
    /// Iterations on each multigrid block level. Reference: 20.
    pub multigrid_iterations: usize,
    /// Cap on the multigrid depth (the reference's depth is at most `pyramid_levels − 1`).
    pub max_multigrid_depth: usize,
    /// Horizontal bands of rows that every belief-propagation sweep treats as separate images;
    /// messages across band boundaries are sent after each sweep. 1 is the reference's sequential
    /// schedule; more bands change the result slightly (a different message order). The bands used
    /// to be swept in parallel; the vector sweeps are faster on one thread and run them one after
    /// the other, with the same messages.
    pub bp_bands: usize,
    /// Use the message-passing code specialised for the default window sizes; `false` runs the
    /// generic code (identical results; exists to measure the difference).
    pub specialised_kernels: bool,
}

impl Default for SiftFlowConfig {
    fn default() -> Self {
        Self {
            pyramid_levels: 4,
            top_search_radius_px: 10,
            search_radius_px: 2,
            top_iterations: 60,
            iterations: 30,
            smoothness_weight: 2.0 * 255.0,
            smoothness_truncation: 40.0 * 255.0,
            flow_magnitude_weight: 0.005 * 255.0,
            truncate_data_cost: false,
            pyramid_sigma_px: 0.67,
            subpixel: SubpixelRefinement::DataCostParabola,
            l1_kernel: L1Kernel::Auto,
            specialised_kernels: true,
            multigrid: true,
            multigrid_iterations: 20,
            max_multigrid_depth: 8,
            bp_bands: 2,
        }
    }
}

impl SiftFlowConfig {
    /// The reference's parameters with far fewer belief-propagation iterations (4 per level, 20 at
    /// the top, 4 per multigrid block level): the multigrid start makes the extra iterations of the
    /// reference nearly useless. Two bands of rows (the schedule registration was measured with;
    /// on the synthetic block scene it registers better than one band). Measured on the shared
    /// pairs: EPE 0.278 px (505×275) and 0.271 px (1010×550) against 0.277 and 0.270 with the
    /// defaults, at about a third of the CPU time.
    pub fn fast() -> Self {
        Self {
            iterations: 4,
            top_iterations: 20,
            multigrid_iterations: 4,
            bp_bands: 2,
            ..Self::default()
        }
    }

    /// Checks every field once; call before the hot path.
    pub fn validate(&self) -> Result<(), FlowError> {
        let bad =
            |field: &'static str, reason: String| Err(FlowError::InvalidConfig { field, reason });
        if !(1..=8).contains(&self.pyramid_levels) {
            return bad(
                "pyramid_levels",
                format!("{} is not in 1..=8", self.pyramid_levels),
            );
        }
        let largest_radius = self
            .top_search_radius_px
            .max(self.search_radius_px + self.pyramid_levels);
        if self.top_search_radius_px == 0 || 2 * largest_radius + 1 > MAX_LABELS {
            return bad(
                "top_search_radius_px",
                format!(
                    "search windows must have 1..={} px half-width",
                    (MAX_LABELS - 1) / 2 - 8
                ),
            );
        }
        for (field, value) in [
            ("smoothness_weight", self.smoothness_weight),
            ("smoothness_truncation", self.smoothness_truncation),
            ("flow_magnitude_weight", self.flow_magnitude_weight),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, format!("{value} is not a finite value >= 0"));
            }
        }
        if !(1..=64).contains(&self.bp_bands) {
            return bad("bp_bands", format!("{} is not in 1..=64", self.bp_bands));
        }
        if !(self.pyramid_sigma_px.is_finite() && self.pyramid_sigma_px > 0.0) {
            return bad(
                "pyramid_sigma_px",
                format!("{} is not > 0", self.pyramid_sigma_px),
            );
        }
        Ok(())
    }

    pub(super) fn level_radius(&self, level: usize, top_level: usize) -> usize {
        if level == top_level {
            self.top_search_radius_px
        } else {
            self.search_radius_px + level
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_rejects_unknown_fields_and_bad_values() {
        assert!(serde_json::from_str::<SiftFlowConfig>(r#"{"alpha": 1.0}"#).is_err());
        let parsed: SiftFlowConfig = serde_json::from_str(r#"{"iterations": 5}"#).unwrap();
        assert_eq!(parsed.iterations, 5);
        assert_eq!(parsed.top_search_radius_px, 10);
        let bad = SiftFlowConfig {
            top_search_radius_px: 40,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let bad = SiftFlowConfig {
            smoothness_weight: f32::NAN,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}
