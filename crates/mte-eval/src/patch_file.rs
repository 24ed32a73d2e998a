//! A trained physical patch on disk: `patch.png` (the texture, RGB, one pixel per
//! observation pixel) and `patch.json` ([`PatchMeta`]: where it sits in the world, how it was
//! trained, against which policy).

use std::fs;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mte_policy::patch::{Ascent, PatchConfig, PatchReport, Placement};
use mte_sim::Patch;
use serde::{Deserialize, Serialize};

/// Format tag of `patch.json`.
pub const PATCH_FORMAT: &str = "mte-patch-v1";
/// Texture file name.
pub const PNG: &str = "patch.png";
/// Metadata file name.
pub const JSON: &str = "patch.json";

/// Errors reading or writing a patch directory.
#[derive(Debug, thiserror::Error)]
pub enum PatchFileError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Malformed JSON.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Cause.
        source: serde_json::Error,
    },
    /// A PNG that is not an 8-bit RGB square of the recorded side, or undecodable.
    #[error("{path}: {reason}")]
    Png {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The texture and metadata do not make a patch.
    #[error(transparent)]
    Patch(#[from] mte_sim::PatchError),
}

/// `patch.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatchMeta {
    /// Always [`PATCH_FORMAT`].
    pub format: String,
    /// Texture side (observation px).
    pub side: usize,
    /// Centre (world px, 512 x 512 canvas, y down).
    pub center: [f64; 2],
    /// Top-left pixel in the policy's frame at evaluation (and at training, when fixed).
    pub origin: [usize; 2],
    /// Where training placed the texture in each batch (absent in files written before
    /// placements existed: fixed at `origin`).
    #[serde(default = "fixed_placement")]
    pub placement: Placement,
    /// What the texture is: trained, or a control made from a trained patch (absent in
    /// older files: trained, or the mean-colour control when `epochs` is 0).
    #[serde(default)]
    pub control: Option<ControlKind>,
    /// Frame (width, height) it was trained for.
    pub frame: [usize; 2],
    /// Ascent rule.
    pub ascent: Ascent,
    /// Step size.
    pub step: f64,
    /// Epochs.
    pub epochs: usize,
    /// Batches per epoch.
    pub batches_per_epoch: usize,
    /// Windows per batch.
    pub batch_size: usize,
    /// Seed.
    pub seed: u64,
    /// Mean policy loss in the first epoch.
    pub initial_loss: f64,
    /// Mean policy loss per epoch.
    pub epoch_loss: Vec<f64>,
    /// Checkpoint attacked.
    pub policy: String,
    /// Present when encoder fine-tuning carried the texture on (`mte defend finetune
    /// --regenerate`); the fields above still describe the texture it started from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub regenerated: Option<Regeneration>,
}

/// How encoder fine-tuning regenerated a patch: before each fine-tuning step, one signed
/// ascent step on the policy loss through the encoder being tuned, with the texture pasted
/// at a position drawn uniformly in the frame (see `mte_policy::patch::finetune_encoder`).
/// At evaluation the texture sits where the patch it started from sat; like every patch file
/// it is stored in 8 bits per channel, so it differs from the last in-memory texture by at
/// most half a level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Regeneration {
    /// The patch directory it started from.
    pub from: String,
    /// The fine-tuned checkpoint: the encoder the last ascent step was taken against.
    pub encoder: String,
    /// Ascent steps taken (one per fine-tuning step).
    pub steps: usize,
    /// Ascent step size (the sign rule; pixel values in [0, 1]).
    pub step: f64,
    /// Windows per batch.
    pub batch_size: usize,
    /// Fine-tuning seed (windows, positions, noise and timesteps).
    pub seed: u64,
    /// Mean policy loss under the patch at the first and last up-to-100 ascent steps.
    pub first_loss: f64,
    /// See `first_loss`.
    pub last_loss: f64,
}

impl PatchMeta {
    /// Metadata of a training run.
    pub fn new(
        cfg: &PatchConfig,
        report: &PatchReport,
        center: [f64; 2],
        frame: [usize; 2],
        policy: &Path,
    ) -> Self {
        PatchMeta {
            format: PATCH_FORMAT.into(),
            side: report.side,
            center,
            origin: [report.origin.0, report.origin.1],
            placement: cfg.placement.clone(),
            control: None,
            frame,
            ascent: cfg.ascent,
            step: cfg.step,
            epochs: cfg.epochs,
            batches_per_epoch: cfg.batches_per_epoch,
            batch_size: cfg.batch_size,
            seed: cfg.seed,
            initial_loss: report.initial_loss,
            epoch_loss: report.epoch_loss.clone(),
            policy: policy.display().to_string(),
            regenerated: None,
        }
    }

    /// This patch's metadata for the texture that regeneration `r` made from it: the same
    /// placement and training record, no longer a control.
    pub fn regenerated(self, r: Regeneration) -> Self {
        PatchMeta {
            control: None,
            regenerated: Some(r),
            ..self
        }
    }
}

/// Write `patch.png` and `patch.json` into `dir` (created if needed).
pub fn save(dir: &Path, meta: &PatchMeta, rgb: &[u8]) -> Result<(), PatchFileError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| PatchFileError::Io { path, source }
    };
    fs::create_dir_all(dir).map_err(io(dir))?;
    let png_path = dir.join(PNG);
    let file = fs::File::create(&png_path).map_err(io(&png_path))?;
    let side = u32::try_from(meta.side).map_err(|_| PatchFileError::Png {
        path: png_path.clone(),
        reason: format!("side {} too large", meta.side),
    })?;
    let mut enc = png::Encoder::new(BufWriter::new(file), side, side);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let png_err = |e: png::EncodingError| PatchFileError::Png {
        path: png_path.clone(),
        reason: e.to_string(),
    };
    let mut w = enc.write_header().map_err(png_err)?;
    w.write_image_data(rgb).map_err(png_err)?;
    w.finish().map_err(png_err)?;
    let json_path = dir.join(JSON);
    let text = serde_json::to_string_pretty(meta).map_err(|source| PatchFileError::Json {
        path: json_path.clone(),
        source,
    })?;
    fs::write(&json_path, text + "\n").map_err(io(&json_path))
}

/// Read a patch directory: its metadata and the world-placed [`Patch`].
pub fn load(dir: &Path) -> Result<(PatchMeta, Patch), PatchFileError> {
    let json_path = dir.join(JSON);
    let text = fs::read_to_string(&json_path).map_err(|source| PatchFileError::Io {
        path: json_path.clone(),
        source,
    })?;
    let meta: PatchMeta = serde_json::from_str(&text).map_err(|source| PatchFileError::Json {
        path: json_path.clone(),
        source,
    })?;
    let png_path = dir.join(PNG);
    let bad = |reason: String| PatchFileError::Png {
        path: png_path.clone(),
        reason,
    };
    let file = fs::File::open(&png_path).map_err(|source| PatchFileError::Io {
        path: png_path.clone(),
        source,
    })?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| bad(e.to_string()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| bad(e.to_string()))?;
    if info.color_type != png::ColorType::Rgb
        || info.bit_depth != png::BitDepth::Eight
        || info.width as usize != meta.side
        || info.height as usize != meta.side
    {
        return Err(bad(format!(
            "{}x{} {:?} {:?}: expected a {s}x{s} 8-bit RGB image (patch.json side {s})",
            info.width,
            info.height,
            info.color_type,
            info.bit_depth,
            s = meta.side
        )));
    }
    buf.truncate(info.buffer_size());
    let patch = Patch::new(buf, meta.side, meta.center)?;
    Ok((meta, patch))
}

fn fixed_placement() -> Placement {
    Placement::Fixed
}

/// The controls of a trained patch: the same square at the same world position, so that the
/// adversarial patch's effect beyond a control is the effect of its pattern, not of the
/// occlusion.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ControlKind {
    /// Filled with the patch's mean colour (per channel, rounded): the same area and mean
    /// intensity.
    MeanColour,
    /// Mid-grey (128, 128, 128): the texture patch training starts from.
    Grey,
    /// Independent uniform random bytes per pixel and channel (seeded): a textured square
    /// with no optimisation behind it.
    Noise {
        /// Seed of the noise.
        seed: u64,
    },
}

impl std::fmt::Display for ControlKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::MeanColour => f.write_str("mean-colour"),
            Self::Grey => f.write_str("grey"),
            Self::Noise { seed } => write!(f, "noise (seed {seed})"),
        }
    }
}

/// The control texture of `kind` for `rgb` (RGB u8, row-major).
pub fn control_texture(rgb: &[u8], kind: ControlKind) -> Vec<u8> {
    match kind {
        ControlKind::MeanColour => {
            let n = (rgb.len() / 3).max(1) as f64;
            let mean: Vec<u8> = (0..3)
                .map(|c| {
                    let sum: f64 = rgb.iter().skip(c).step_by(3).map(|&v| f64::from(v)).sum();
                    (sum / n).round().clamp(0.0, 255.0) as u8
                })
                .collect();
            (0..rgb.len()).map(|i| mean[i % 3]).collect()
        }
        ControlKind::Grey => vec![128; rgb.len()],
        ControlKind::Noise { seed } => {
            use rand::{RngCore, SeedableRng};
            let mut out = vec![0; rgb.len()];
            rand_chacha::ChaCha8Rng::seed_from_u64(seed).fill_bytes(&mut out);
            out
        }
    }
}

/// Writes into `dst` the `kind` control of the patch in `src` (see [`ControlKind`]). The
/// metadata is the source's with `epochs = 0`, `step = 0`, no loss curve and `control` set.
/// Returns the control's metadata.
pub fn control(src: &Path, dst: &Path, kind: ControlKind) -> Result<PatchMeta, PatchFileError> {
    let (meta, patch) = load(src)?;
    let texture = control_texture(patch.rgb(), kind);
    let control = PatchMeta {
        step: 0.0,
        epochs: 0,
        initial_loss: 0.0,
        epoch_loss: Vec::new(),
        control: Some(kind),
        ..meta
    };
    save(dst, &control, &texture)?;
    Ok(control)
}

/// [`control`] with [`ControlKind::MeanColour`].
pub fn mean_colour_control(src: &Path, dst: &Path) -> Result<PatchMeta, PatchFileError> {
    control(src, dst, ControlKind::MeanColour)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trained patch's report and metadata: `side` px of `value`, at `origin` in a 96 x 96
    /// frame, centred at `center` in the world.
    fn trained(
        value: f32,
        side: usize,
        origin: (usize, usize),
        center: [f64; 2],
    ) -> (PatchReport, PatchMeta) {
        let report = PatchReport {
            texture: vec![value; 3 * side * side],
            side,
            origin,
            initial_loss: 0.1,
            epoch_loss: vec![0.2],
        };
        let meta = PatchMeta::new(
            &PatchConfig::default(),
            &report,
            center,
            [96, 96],
            Path::new("ck"),
        );
        (report, meta)
    }

    #[test]
    fn the_control_is_the_patch_s_mean_colour_at_the_same_place() {
        let (a, b) = (
            tempfile::tempdir().expect("tmp"),
            tempfile::tempdir().expect("tmp"),
        );
        let (_, meta) = trained(0.5, 4, (10, 20), [100.0, 300.0]);
        // Red channel 0 or 255 alternately (mean 127.5 -> 128), green 10, blue 0..16.
        let rgb: Vec<u8> = (0..16)
            .flat_map(|i| [if i % 2 == 0 { 0 } else { 255 }, 10, i as u8])
            .collect();
        save(a.path(), &meta, &rgb).expect("save");
        let c = mean_colour_control(a.path(), b.path()).expect("control");
        let (m, p) = load(b.path()).expect("load");
        assert_eq!(m, c);
        assert_eq!(
            (m.side, m.center, m.origin, m.epochs),
            (4, [100.0, 300.0], [10, 20], 0)
        );
        assert!(
            p.rgb().chunks(3).all(|px| px == [128, 10, 8]),
            "{:?}",
            &p.rgb()[..6]
        );
        assert!(mean_colour_control(Path::new("no/such/patch"), b.path()).is_err());
    }

    #[test]
    fn grey_and_noise_controls_keep_size_and_place() {
        let (a, b, c) = (
            tempfile::tempdir().expect("tmp"),
            tempfile::tempdir().expect("tmp"),
            tempfile::tempdir().expect("tmp"),
        );
        let (report, meta) = trained(0.9, 8, (5, 6), [90.0, 400.0]);
        save(a.path(), &meta, &report.rgb_u8()).expect("save");
        let grey = control(a.path(), b.path(), ControlKind::Grey).expect("grey");
        let (m, p) = load(b.path()).expect("load grey");
        assert_eq!(
            (m.side, m.center, m.control),
            (8, [90.0, 400.0], Some(ControlKind::Grey))
        );
        assert_eq!(grey, m);
        assert!(p.rgb().iter().all(|&v| v == 128));
        let noise = ControlKind::Noise { seed: 3 };
        control(a.path(), c.path(), noise).expect("noise");
        let (m, p) = load(c.path()).expect("load noise");
        assert_eq!((m.origin, m.control), ([5, 6], Some(noise)));
        let distinct: std::collections::BTreeSet<u8> = p.rgb().iter().copied().collect();
        assert!(
            distinct.len() > 100,
            "noise has {} distinct values",
            distinct.len()
        );
        assert_eq!(
            p.rgb(),
            &control_texture(&report.rgb_u8(), noise)[..],
            "seeded"
        );
        assert_ne!(
            control_texture(&[0; 12], noise),
            control_texture(&[0; 12], ControlKind::Noise { seed: 4 })
        );
    }

    #[test]
    fn files_without_a_placement_read_as_fixed() {
        let dir = tempfile::tempdir().expect("tmp");
        let (report, meta) = trained(0.25, 4, (1, 2), [256.0, 256.0]);
        save(dir.path(), &meta, &report.rgb_u8()).expect("save");
        let mut v: serde_json::Value =
            serde_json::from_str(&fs::read_to_string(dir.path().join(JSON)).expect("read"))
                .expect("json");
        let obj = v.as_object_mut().expect("object");
        obj.remove("placement");
        obj.remove("control");
        fs::write(dir.path().join(JSON), v.to_string()).expect("write");
        let (m, _) = load(dir.path()).expect("old file");
        assert_eq!((m.placement, m.control), (Placement::Fixed, None));
        assert_eq!(m.regenerated, None, "a file without the field");
    }

    #[test]
    fn a_regenerated_patch_keeps_its_place_and_records_the_regeneration() {
        let (a, b, c) = (
            tempfile::tempdir().expect("tmp"),
            tempfile::tempdir().expect("tmp"),
            tempfile::tempdir().expect("tmp"),
        );
        let (report, meta) = trained(0.3, 6, (7, 9), [80.0, 420.0]);
        save(a.path(), &meta, &report.rgb_u8()).expect("save");
        // A control that regeneration carried on is no longer a control.
        let grey = control(a.path(), b.path(), ControlKind::Grey).expect("grey");
        let r = Regeneration {
            from: b.path().display().to_string(),
            encoder: "tuned".into(),
            steps: 3000,
            step: 1.5e-3,
            batch_size: 16,
            seed: 7,
            first_loss: 0.09,
            last_loss: 0.17,
        };
        let regen = grey.clone().regenerated(r.clone());
        let rgb: Vec<u8> = (0..6 * 6 * 3).map(|i| (i * 7 % 256) as u8).collect();
        save(c.path(), &regen, &rgb).expect("save regenerated");
        let (m, p) = load(c.path()).expect("load regenerated");
        assert_eq!(m, regen);
        assert_eq!((m.control, m.regenerated), (None, Some(r)));
        assert_eq!((m.origin, m.center, m.side), (grey.origin, grey.center, 6));
        assert_eq!(p.rgb(), &rgb[..]);
        // Only regenerated files carry the field.
        let text = fs::read_to_string(b.path().join(JSON)).expect("read");
        assert!(!text.contains("regenerated"), "{text}");
    }

    #[test]
    fn round_trips_and_rejects_a_mismatched_png() {
        let dir = tempfile::tempdir().expect("tmp");
        let (_, meta) = trained(0.25, 16, (40, 40), [256.0, 256.0]);
        let rgb: Vec<u8> = (0..16 * 16 * 3).map(|i| (i % 251) as u8).collect();
        save(dir.path(), &meta, &rgb).expect("save");
        let (m, p) = load(dir.path()).expect("load");
        assert_eq!(m, meta);
        assert_eq!(p.rgb(), &rgb[..]);
        assert_eq!(p.origin(96, 96).expect("fits"), (40, 40));
        let mut wrong = meta.clone();
        wrong.side = 8;
        let text = serde_json::to_string(&wrong).expect("json");
        fs::write(dir.path().join(JSON), text).expect("write");
        let e = load(dir.path()).expect_err("16 px png, 8 px metadata");
        assert!(e.to_string().contains("expected a 8x8"), "{e}");
    }
}
