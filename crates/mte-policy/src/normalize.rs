//! LeRobot's normalisation modes (`MEAN_STD`, `MIN_MAX`, `IDENTITY`), per feature.
//!
//! `MEAN_STD`: `(x - mean) / (std + 1e-8)`. `MIN_MAX`: `2 (x - min) / (max - min + 1e-8) - 1`,
//! mapping [min, max] to [-1, 1]; the inverse is `(y + 1) / 2 (max - min + 1e-8) + min`.
//! (LeRobot's processor substitutes the epsilon only where `max == min`; with f32 stats the
//! two agree to ~1e-8 relative, far below anything a policy can resolve.)

use serde::{Deserialize, Serialize};

use crate::error::{PolicyError, config_err};

/// LeRobot's epsilon in both modes.
pub const EPS: f32 = 1e-8;

/// A camera's `MEAN_STD` normalisation: per channel `(x - mean) / (std + eps)` of
/// `(B, 3, H, W)` frames in [0, 1] (LeRobot's VISUAL features), in the frames' dtype and on
/// their device, so gradients flow through it to the pixels.
#[derive(Clone, Debug)]
pub struct ImageNorm {
    /// The channel means (R, G, B), in the frames' [0, 1] units.
    mean: [f32; 3],
    /// The channel stds with [`EPS`] added.
    std: [f32; 3],
    /// `mean` and `std` as `(1, 3, 1, 1)` f32 tensors on the CPU, built once: on CPU f32
    /// frames [`ImageNorm::apply`] uses them as they are (no tensor built per call).
    mean_t: candle_core::Tensor,
    std_t: candle_core::Tensor,
}

impl PartialEq for ImageNorm {
    fn eq(&self, other: &Self) -> bool {
        self.mean == other.mean && self.std == other.std
    }
}

impl ImageNorm {
    /// From camera `name`'s statistics, which must hold 3 finite channel means and 3 finite,
    /// non-negative channel stds.
    pub fn mean_std(name: &str, stats: Option<&Stats>) -> Result<Self, PolicyError> {
        let empty = Stats::default();
        let s = stats.unwrap_or(&empty);
        let (Ok(mean), Ok(std)) = (
            <[f32; 3]>::try_from(s.mean.as_slice()),
            <[f32; 3]>::try_from(s.std.as_slice()),
        ) else {
            return Err(config_err(
                "stats",
                format!("{name}: mean {:?}, std {:?}", s.mean, s.std),
                "3 channel means and stds",
            ));
        };
        if mean.iter().any(|m| !m.is_finite()) || std.iter().any(|v| !(v.is_finite() && *v >= 0.0))
        {
            return Err(config_err(
                "stats",
                format!("{name}: mean {mean:?}, std {std:?}"),
                "finite channel means and finite, non-negative stds",
            ));
        }
        let std = std.map(|v| v + EPS);
        let channel = |v: [f32; 3]| {
            candle_core::Tensor::from_vec(v.to_vec(), (1, 3, 1, 1), &candle_core::Device::Cpu)
                .map_err(|e| config_err("stats", format!("{name}: {e}"), "3 channel values"))
        };
        Ok(Self {
            mean_t: channel(mean)?,
            std_t: channel(std)?,
            mean,
            std,
        })
    }

    /// The camera normalisation for `mode` (LeRobot's VISUAL mapping; absent means
    /// IDENTITY): MEAN_STD from camera `name`'s statistics, IDENTITY none, and any other
    /// mode a config error naming `normalization_mapping.VISUAL`.
    pub fn for_mode(
        mode: NormMode,
        name: &str,
        stats: Option<&Stats>,
    ) -> Result<Option<Self>, PolicyError> {
        match mode {
            NormMode::MeanStd => Self::mean_std(name, stats).map(Some),
            NormMode::Identity => Ok(None),
            other => Err(config_err(
                "normalization_mapping.VISUAL",
                other,
                "MEAN_STD or IDENTITY",
            )),
        }
    }

    /// The normalised frames.
    pub fn apply(&self, img: &candle_core::Tensor) -> candle_core::Result<candle_core::Tensor> {
        // Same device and dtype: the cached tensors themselves (to_device and to_dtype
        // return a shallow clone then); elsewhere a 3-value copy per call.
        let fit = |t: &candle_core::Tensor| t.to_device(img.device())?.to_dtype(img.dtype());
        img.broadcast_sub(&fit(&self.mean_t)?)?
            .broadcast_div(&fit(&self.std_t)?)
    }
}

/// How a feature is normalised (LeRobot's `normalization_mapping` values).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum NormMode {
    /// `(x - mean) / (std + eps)`.
    MeanStd,
    /// To [-1, 1] from [min, max].
    MinMax,
    /// Unchanged.
    Identity,
}

/// Statistics of one feature, one value per coordinate (per channel for images).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Stats {
    /// Coordinate-wise minimum.
    #[serde(default)]
    pub min: Vec<f32>,
    /// Coordinate-wise maximum.
    #[serde(default)]
    pub max: Vec<f32>,
    /// Coordinate-wise mean.
    #[serde(default)]
    pub mean: Vec<f32>,
    /// Coordinate-wise standard deviation.
    #[serde(default)]
    pub std: Vec<f32>,
}

/// A normaliser for one feature of dimension `dim` (images: channels, applied per pixel).
#[derive(Clone, Debug, PartialEq)]
pub struct Normalizer {
    mode: NormMode,
    /// Per coordinate: y = (x - offset) * scale - shift.
    offset: Vec<f32>,
    scale: Vec<f32>,
    shift: f32,
}

impl Normalizer {
    /// Build from `stats`; the statistics the mode needs must have `dim` finite entries.
    pub fn new(
        name: &'static str,
        mode: NormMode,
        stats: &Stats,
        dim: usize,
    ) -> Result<Self, PolicyError> {
        let check = |v: &Vec<f32>, what: &str| -> Result<(), PolicyError> {
            if v.len() != dim || v.iter().any(|x| !x.is_finite()) {
                return Err(config_err(
                    name,
                    format!("{what} = {v:?}"),
                    format!("{dim} finite values"),
                ));
            }
            Ok(())
        };
        match mode {
            NormMode::Identity => Ok(Normalizer {
                mode,
                offset: vec![0.0; dim],
                scale: vec![1.0; dim],
                shift: 0.0,
            }),
            NormMode::MeanStd => {
                check(&stats.mean, "mean")?;
                check(&stats.std, "std")?;
                Ok(Normalizer {
                    mode,
                    offset: stats.mean.clone(),
                    scale: stats.std.iter().map(|s| 1.0 / (s + EPS)).collect(),
                    shift: 0.0,
                })
            }
            NormMode::MinMax => {
                check(&stats.min, "min")?;
                check(&stats.max, "max")?;
                Ok(Normalizer {
                    mode,
                    offset: stats.min.clone(),
                    scale: stats
                        .min
                        .iter()
                        .zip(&stats.max)
                        .map(|(lo, hi)| 2.0 / (hi - lo + EPS))
                        .collect(),
                    shift: 1.0,
                })
            }
        }
    }

    /// The mode.
    pub fn mode(&self) -> NormMode {
        self.mode
    }

    /// Coordinates per row.
    pub fn dim(&self) -> usize {
        self.offset.len()
    }

    /// Normalise rows of `dim` values in place.
    pub fn normalize(&self, x: &mut [f32]) {
        let d = self.dim();
        for (i, v) in x.iter_mut().enumerate() {
            let k = i % d;
            *v = (*v - self.offset[k]) * self.scale[k] - self.shift;
        }
    }

    /// Undo [`Normalizer::normalize`] in place.
    pub fn unnormalize(&self, y: &mut [f32]) {
        let d = self.dim();
        for (i, v) in y.iter_mut().enumerate() {
            let k = i % d;
            *v = (*v + self.shift) / self.scale[k] + self.offset[k];
        }
    }

    /// d(normalised)/d(raw) per coordinate (to move gradients between the two spaces).
    pub fn scale(&self) -> &[f32] {
        &self.scale
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_max_maps_to_unit_interval_and_back() {
        let s = Stats {
            min: vec![12.0, 25.0],
            max: vec![511.0, 511.0],
            ..Default::default()
        };
        let n = Normalizer::new("action", NormMode::MinMax, &s, 2).expect("valid");
        let mut x = vec![12.0, 511.0, 261.5, 268.0];
        n.normalize(&mut x);
        assert!((x[0] + 1.0).abs() < 1e-6 && (x[1] - 1.0).abs() < 1e-6);
        assert!(x[2].abs() < 1e-6 && x[3].abs() < 1e-6);
        n.unnormalize(&mut x);
        assert!((x[2] - 261.5).abs() < 1e-4 && (x[1] - 511.0).abs() < 1e-4);
    }

    #[test]
    fn mean_std_and_errors() {
        let s = Stats {
            mean: vec![0.5],
            std: vec![0.25],
            ..Default::default()
        };
        let n = Normalizer::new("image", NormMode::MeanStd, &s, 1).expect("valid");
        let mut x = vec![1.0];
        n.normalize(&mut x);
        assert!((x[0] - 2.0).abs() < 1e-6);
        let e = Normalizer::new("state", NormMode::MinMax, &s, 1).expect_err("no min");
        assert!(e.to_string().contains("state"), "{e}");
    }

    #[test]
    fn image_norm_is_per_channel_in_the_frames_dtype() -> candle_core::Result<()> {
        use candle_core::{DType, Device, Tensor};
        let s = Stats {
            mean: vec![0.5, 0.25, 0.0],
            std: vec![0.5, 0.25, 2.0],
            ..Default::default()
        };
        let n = ImageNorm::mean_std("observation.image", Some(&s)).expect("3 channels");
        // Two frames of 2 x 1 pixels, channel c of pixel p reading 0.1 c + 0.05 p.
        let v: Vec<f32> = (0..12)
            .map(|i| 0.1 * ((i / 2) % 3) as f32 + 0.05 * (i % 2) as f32)
            .collect();
        let img = Tensor::from_vec(v.clone(), (2, 3, 2, 1), &Device::Cpu)?;
        for dtype in [DType::F32, DType::F64] {
            let out = n.apply(&img.to_dtype(dtype)?)?;
            assert_eq!(out.dtype(), dtype);
            let got = out.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
            for (i, (g, x)) in got.iter().zip(&v).enumerate() {
                let c = (i / 2) % 3;
                let want = (x - s.mean[c]) / (s.std[c] + EPS);
                assert!(
                    (g - want).abs() < 1e-6,
                    "{dtype:?} value {i}: {g} vs {want}"
                );
            }
        }
        // Applied twice, the same values (the cached channel tensors are not consumed).
        let a = n.apply(&img)?.flatten_all()?.to_vec1::<f32>()?;
        let b = n.apply(&img)?.flatten_all()?.to_vec1::<f32>()?;
        assert_eq!(a, b);
        let two = Stats {
            mean: vec![0.5, 0.5],
            std: vec![1.0, 1.0],
            ..Default::default()
        };
        let e = ImageNorm::mean_std("observation.image", Some(&two)).expect_err("2 channels");
        assert!(e.to_string().contains("observation.image"), "{e}");
        // Non-finite or negative statistics are refused by name, never turned into NaN.
        for (mean, std) in [
            (vec![f32::NAN, 0.5, 0.5], vec![1.0; 3]),
            (vec![0.5; 3], vec![1.0, f32::INFINITY, 1.0]),
            (vec![0.5; 3], vec![1.0, 1.0, -0.5]),
        ] {
            let bad = Stats {
                mean,
                std,
                ..Default::default()
            };
            let e = ImageNorm::mean_std("observation.images.top", Some(&bad))
                .expect_err("non-finite or negative statistics");
            let msg = e.to_string();
            assert!(
                msg.contains("observation.images.top") && msg.contains("finite"),
                "{msg}"
            );
        }
        // Equality compares the statistics.
        let same = ImageNorm::mean_std("other", Some(&s)).expect("3 channels");
        assert_eq!(n, same);
        let shifted = Stats {
            mean: vec![0.5, 0.25, 0.125],
            ..s.clone()
        };
        assert_ne!(
            n,
            ImageNorm::mean_std("other", Some(&shifted)).expect("3 channels")
        );
        Ok(())
    }
}
