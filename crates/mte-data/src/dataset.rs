//! The `mte-demo-v1` dataset: writing episodes as they are produced, and loading them back.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::DataError;
use crate::npy::{DType, NpyArray, NpyWriter};
use crate::stats::{FeatureStats, StatsAccumulator};

/// Format tag written to `info.json`.
pub const FORMAT: &str = "mte-demo-v1";

/// Features with a fixed meaning; names are LeRobot's.
pub mod names {
    /// Agent position (2, px): LeRobot's `observation.state` for PushT.
    pub const STATE: &str = "observation.state";
    /// Block keypoints (16, px): LeRobot's `observation.environment_state`.
    pub const ENV_STATE: &str = "observation.environment_state";
    /// gym-pusht's 5-vector `state` observation [agent x, y, block x, y, angle mod 2 pi].
    pub const PUSHT_STATE: &str = "observation.pusht_state";
    /// Camera frame (H, W, 3) u8: LeRobot's `observation.image`.
    pub const IMAGE: &str = "observation.image";
    /// The wrist camera's frame (H, W, 3) u8, in LeRobot's `observation.images.<camera>`
    /// form (robomimic: `robot0_eye_in_hand_image`).
    pub const WRIST_IMAGE: &str = "observation.images.wrist";
    /// Agent target (2, px).
    pub const ACTION: &str = "action";
    /// Episode of each frame.
    pub const EPISODE_INDEX: &str = "episode_index";
    /// Frame index within its episode.
    pub const FRAME_INDEX: &str = "frame_index";
    /// Seconds since the episode start (frame_index / fps).
    pub const TIMESTAMP: &str = "timestamp";
    /// Reward after the frame's action.
    pub const REWARD: &str = "next.reward";
    /// Episode over after the frame's action.
    pub const DONE: &str = "next.done";
    /// Coverage > 0.95 after the frame's action.
    pub const SUCCESS: &str = "next.success";
}

/// One stored feature.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Feature {
    /// Element type.
    pub dtype: DType,
    /// Shape of one frame's value.
    pub shape: Vec<usize>,
    /// File under `data/`.
    pub file: String,
    /// Units and conventions.
    pub description: String,
}

/// `info.json`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Info {
    /// Always [`FORMAT`].
    pub format: String,
    /// Control rate (Hz).
    pub fps: f64,
    /// Number of episodes.
    pub episodes: usize,
    /// Number of frames over all episodes.
    pub frames: usize,
    /// Stored features by name.
    pub features: BTreeMap<String, Feature>,
    /// How the data was made (free-form, e.g. the generation config).
    pub generator: serde_json::Value,
}

impl Info {
    /// Read `dir/info.json` written by [`DatasetWriter`], its format tag checked (what a
    /// caller needs to size a model before loading the arrays).
    pub fn read(dir: &Path) -> Result<Self, DataError> {
        let path = dir.join("info.json");
        let info: Self = read_json(&path)?;
        if info.format != FORMAT {
            return Err(DataError::Format {
                path,
                reason: format!("format {:?}, expected {FORMAT:?}", info.format),
            });
        }
        Ok(info)
    }
}

/// One line of `episodes.jsonl`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpisodeMeta {
    /// Episode index (0-based, consecutive).
    pub index: usize,
    /// Reset seed.
    pub seed: u64,
    /// First frame (global index).
    pub start: usize,
    /// Frames in the episode.
    pub length: usize,
    /// Whether the episode reached coverage > 0.95.
    pub success: bool,
    /// Maximum coverage over the episode.
    pub max_coverage: f64,
}

/// One frame's values, as produced by a generator. Optional features are `None` when not
/// recorded (consistently for a whole dataset); lengths follow the dataset's [`Layout`].
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Robot state (PushT: agent position, px).
    pub state: Vec<f32>,
    /// Environment state (PushT: keypoints, px).
    pub env_state: Option<Vec<f32>>,
    /// gym-pusht state observation.
    pub pusht_state: Option<[f32; 5]>,
    /// Image, HWC u8.
    pub image: Option<Vec<u8>>,
    /// The wrist camera's image, HWC u8.
    pub wrist_image: Option<Vec<u8>>,
    /// Action (PushT: agent target, px).
    pub action: Vec<f32>,
    /// Reward after the action.
    pub reward: f32,
    /// Episode over after the action.
    pub done: bool,
    /// Success after the action.
    pub success: bool,
}

/// What a dataset stores per frame: feature sizes and what they mean (written to
/// `info.json`'s descriptions).
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// `observation.state`: length and description.
    pub state: (usize, String),
    /// `observation.environment_state`, if stored: length and description.
    pub env_state: Option<(usize, String)>,
    /// Whether gym-pusht's 5-vector `observation.pusht_state` is stored.
    pub pusht_state: bool,
    /// `observation.image` (height, width), if stored.
    pub image_hw: Option<(usize, usize)>,
    /// `observation.images.wrist` (height, width), if stored.
    pub wrist_hw: Option<(usize, usize)>,
    /// `action`: length and description.
    pub action: (usize, String),
    /// What `next.reward` is.
    pub reward: String,
    /// What `next.success` is.
    pub success: String,
}

impl Layout {
    /// PushT's features (agent position, keypoints, targets in px).
    pub fn pusht(
        with_env_state: bool,
        with_pusht_state: bool,
        image_hw: Option<(usize, usize)>,
    ) -> Self {
        Self {
            state: (2, "agent position [x, y] (px, y down)".into()),
            env_state: with_env_state.then(|| (16, "8 block vertices, bar then stem (px)".into())),
            pusht_state: with_pusht_state,
            image_hw,
            wrist_hw: None,
            action: (2, "agent target [x, y] (px)".into()),
            reward: "clip(coverage / 0.95, 0, 1) after the action".into(),
            success: "coverage > 0.95 after the action".into(),
        }
    }
}

struct Column {
    name: &'static str,
    writer: NpyWriter,
    stats: Option<StatsAccumulator>,
}

/// Writes a dataset episode by episode; every [`DatasetWriter::push_episode`] appends to the
/// arrays. [`DatasetWriter::finish`] writes the headers, `info.json` and `stats.json`.
pub struct DatasetWriter {
    dir: PathBuf,
    fps: f64,
    columns: Vec<Column>,
    features: BTreeMap<String, Feature>,
    episodes: Vec<EpisodeMeta>,
    episodes_file: fs::File,
    frames: usize,
    layout: Layout,
}

impl DatasetWriter {
    /// Create `dir` (it must not already hold a dataset) for PushT's features.
    pub fn create(
        dir: &Path,
        fps: f64,
        with_env_state: bool,
        with_pusht_state: bool,
        image_hw: Option<(usize, usize)>,
    ) -> Result<Self, DataError> {
        Self::create_with(
            dir,
            fps,
            Layout::pusht(with_env_state, with_pusht_state, image_hw),
        )
    }

    /// Create `dir` (it must not already hold a dataset) for the features of `layout`.
    pub fn create_with(dir: &Path, fps: f64, layout: Layout) -> Result<Self, DataError> {
        if dir.join("info.json").exists() {
            return Err(DataError::Format {
                path: dir.to_path_buf(),
                reason: "already holds a dataset (info.json exists); choose a new directory".into(),
            });
        }
        let data = dir.join("data");
        fs::create_dir_all(&data).map_err(|e| DataError::io(&data, e))?;
        let mut w = DatasetWriter {
            dir: dir.to_path_buf(),
            fps,
            columns: Vec::new(),
            features: BTreeMap::new(),
            episodes: Vec::new(),
            episodes_file: fs::File::create(dir.join("episodes.jsonl"))
                .map_err(|e| DataError::io(dir, e))?,
            frames: 0,
            layout: layout.clone(),
        };
        use names::*;
        w.column(STATE, DType::F32, &[layout.state.0], true, &layout.state.1)?;
        if let Some((n, d)) = &layout.env_state {
            w.column(ENV_STATE, DType::F32, &[*n], true, d)?;
        }
        if layout.pusht_state {
            w.column(
                PUSHT_STATE,
                DType::F32,
                &[5],
                true,
                "[agent x, agent y, block x, block y, block angle mod 2pi] (px, rad)",
            )?;
        }
        if let Some((h, wd)) = layout.image_hw {
            w.column(IMAGE, DType::U8, &[h, wd, 3], true, "RGB frame, HWC u8")?;
        }
        if let Some((h, wd)) = layout.wrist_hw {
            let d = "RGB frame of the wrist camera, HWC u8";
            w.column(WRIST_IMAGE, DType::U8, &[h, wd, 3], true, d)?;
        }
        w.column(
            ACTION,
            DType::F32,
            &[layout.action.0],
            true,
            &layout.action.1,
        )?;
        w.column(
            EPISODE_INDEX,
            DType::I64,
            &[],
            false,
            "episode of the frame",
        )?;
        w.column(
            FRAME_INDEX,
            DType::I64,
            &[],
            false,
            "index within the episode",
        )?;
        w.column(TIMESTAMP, DType::F32, &[], false, "frame_index / fps (s)")?;
        w.column(REWARD, DType::F32, &[], false, &layout.reward)?;
        w.column(
            DONE,
            DType::Bool,
            &[],
            false,
            "episode over after the action",
        )?;
        w.column(SUCCESS, DType::Bool, &[], false, &layout.success)?;
        Ok(w)
    }

    fn column(
        &mut self,
        name: &'static str,
        dtype: DType,
        shape: &[usize],
        stats: bool,
        description: &str,
    ) -> Result<(), DataError> {
        let file = format!("{name}.npy");
        let writer = NpyWriter::create(&self.dir.join("data").join(&file), dtype, shape)?;
        // Frames get per-channel statistics.
        let dim = if dtype == DType::U8 {
            3
        } else {
            shape.iter().product::<usize>().max(1)
        };
        self.columns.push(Column {
            name,
            writer,
            stats: stats.then(|| StatsAccumulator::new(dim)),
        });
        self.features.insert(
            name.to_string(),
            Feature {
                dtype,
                shape: shape.to_vec(),
                file,
                description: description.into(),
            },
        );
        Ok(())
    }

    /// Append one episode's frames and flush its metadata line.
    pub fn push_episode(
        &mut self,
        seed: u64,
        max_coverage: f64,
        frames: &[Frame],
    ) -> Result<(), DataError> {
        let index = self.episodes.len();
        let l = &self.layout;
        for f in frames {
            if f.state.len() != l.state.0
                || f.action.len() != l.action.0
                || f.env_state.as_ref().map(Vec::len) != l.env_state.as_ref().map(|e| e.0)
                || f.pusht_state.is_some() != l.pusht_state
                || f.image.as_ref().map(Vec::len) != l.image_hw.map(|(h, w)| h * w * 3)
                || f.wrist_image.as_ref().map(Vec::len) != l.wrist_hw.map(|(h, w)| h * w * 3)
            {
                return Err(DataError::Format {
                    path: self.dir.clone(),
                    reason: format!(
                        "episode {index}: a frame's features differ from the dataset's"
                    ),
                });
            }
        }
        for col in &mut self.columns {
            for (t, f) in frames.iter().enumerate() {
                use names::*;
                match col.name {
                    STATE => put_f32(col, &f.state)?,
                    ENV_STATE => put_f32(col, f.env_state.as_deref().unwrap_or(&[]))?,
                    PUSHT_STATE => {
                        put_f32(col, f.pusht_state.as_ref().map_or(&[][..], |v| &v[..]))?
                    }
                    IMAGE => put_frame(col, f.image.as_deref())?,
                    WRIST_IMAGE => put_frame(col, f.wrist_image.as_deref())?,
                    ACTION => put_f32(col, &f.action)?,
                    EPISODE_INDEX => col.writer.append_i64(&[index as i64])?,
                    FRAME_INDEX => col.writer.append_i64(&[t as i64])?,
                    TIMESTAMP => col.writer.append_f32(&[(t as f64 / self.fps) as f32])?,
                    REWARD => col.writer.append_f32(&[f.reward])?,
                    DONE => col.writer.append_bool(&[f.done])?,
                    SUCCESS => col.writer.append_bool(&[f.success])?,
                    _ => {}
                }
            }
        }
        let meta = EpisodeMeta {
            index,
            seed,
            start: self.frames,
            length: frames.len(),
            success: frames.iter().any(|f| f.success),
            max_coverage,
        };
        let line = serde_json::to_string(&meta).map_err(|e| DataError::Format {
            path: self.dir.clone(),
            reason: e.to_string(),
        })?;
        writeln!(self.episodes_file, "{line}").map_err(|e| DataError::io(&self.dir, e))?;
        self.episodes_file
            .flush()
            .map_err(|e| DataError::io(&self.dir, e))?;
        self.frames += frames.len();
        self.episodes.push(meta);
        Ok(())
    }

    /// Episodes written so far.
    pub fn episodes(&self) -> &[EpisodeMeta] {
        &self.episodes
    }

    /// Finish the arrays and write `info.json` and `stats.json`.
    pub fn finish(self, generator: serde_json::Value) -> Result<Info, DataError> {
        let mut stats = BTreeMap::new();
        for col in self.columns {
            if let Some(s) = col.stats.as_ref().and_then(StatsAccumulator::finish) {
                stats.insert(col.name.to_string(), s);
            }
            col.writer.finish()?;
        }
        let info = Info {
            format: FORMAT.into(),
            fps: self.fps,
            episodes: self.episodes.len(),
            frames: self.frames,
            features: self.features,
            generator,
        };
        write_json(&self.dir.join("stats.json"), &stats)?;
        write_json(&self.dir.join("info.json"), &info)?;
        Ok(info)
    }
}

fn put_frame(col: &mut Column, img: Option<&[u8]>) -> Result<(), DataError> {
    let img = img.unwrap_or(&[]);
    col.writer.append_u8(img)?;
    if let Some(s) = &mut col.stats {
        s.push_image(img);
    }
    Ok(())
}

fn put_f32(col: &mut Column, v: &[f32]) -> Result<(), DataError> {
    col.writer.append_f32(v)?;
    if let Some(s) = &mut col.stats {
        let row: Vec<f64> = v.iter().map(|&x| f64::from(x)).collect();
        s.push(&row);
    }
    Ok(())
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), DataError> {
    let s = serde_json::to_string_pretty(value).map_err(|e| DataError::Format {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    fs::write(path, s + "\n").map_err(|e| DataError::io(path, e))
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, DataError> {
    let s = fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    serde_json::from_str(&s).map_err(|e| DataError::Format {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })
}

/// A dataset loaded in memory.
#[derive(Clone, Debug)]
pub struct Dataset {
    /// `info.json`.
    pub info: Info,
    /// `episodes.jsonl`.
    pub episodes: Vec<EpisodeMeta>,
    /// `stats.json`.
    pub stats: BTreeMap<String, FeatureStats>,
    /// Float features by name, frames x row length, row-major.
    pub floats: BTreeMap<String, Vec<f32>>,
    /// `observation.image` (frames x H x W x 3), if stored.
    pub images: Option<Vec<u8>>,
    /// Every other camera's frames by feature name (frames x H x W x 3; the wrist camera
    /// as [`names::WRIST_IMAGE`]).
    pub other_images: BTreeMap<String, Vec<u8>>,
}

impl Dataset {
    /// Load `dir` written by [`DatasetWriter`]; every array's row count is checked.
    pub fn load(dir: &Path) -> Result<Self, DataError> {
        let info = Info::read(dir)?;
        let stats = read_json(&dir.join("stats.json"))?;
        let ep_path = dir.join("episodes.jsonl");
        let text = fs::read_to_string(&ep_path).map_err(|e| DataError::io(&ep_path, e))?;
        let episodes = text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| {
                serde_json::from_str(l).map_err(|e| DataError::Format {
                    path: ep_path.clone(),
                    reason: e.to_string(),
                })
            })
            .collect::<Result<Vec<EpisodeMeta>, _>>()?;
        let mut floats = BTreeMap::new();
        let mut images = None;
        let mut other_images = BTreeMap::new();
        for (name, f) in &info.features {
            let path = dir.join("data").join(&f.file);
            let a = NpyArray::read(&path)?;
            if a.rows() != info.frames || a.shape[1..] != f.shape[..] {
                return Err(DataError::Format {
                    path,
                    reason: format!(
                        "shape {:?}, expected ({}, {:?})",
                        a.shape, info.frames, f.shape
                    ),
                });
            }
            match a.dtype {
                DType::F32 => {
                    floats.insert(name.clone(), a.to_f32()?);
                }
                DType::U8 if name == names::IMAGE => images = Some(a.into_u8()?),
                DType::U8 => {
                    other_images.insert(name.clone(), a.into_u8()?);
                }
                DType::I64 => {
                    floats.insert(
                        name.clone(),
                        a.to_i64()?.into_iter().map(|v| v as f32).collect(),
                    );
                }
                DType::Bool => {
                    floats.insert(
                        name.clone(),
                        a.to_bool()?
                            .into_iter()
                            .map(|v| f32::from(u8::from(v)))
                            .collect(),
                    );
                }
            }
        }
        Ok(Dataset {
            info,
            episodes,
            stats,
            floats,
            images,
            other_images,
        })
    }

    /// The datasets one after another, as one: their episodes renumbered in order (each
    /// keeps its seed), `episode_index` and the episodes' start frames offset, the
    /// statistics pooled ([`FeatureStats::pooled`]), the generators listed in order. Every
    /// part must store the same features with the same shapes at the same rate.
    ///
    /// # Errors
    /// No parts, or a part whose features, shapes or fps differ from the first's (named by
    /// its position).
    pub fn concat(parts: Vec<Dataset>) -> Result<Dataset, DataError> {
        let mut parts = parts.into_iter();
        let mut out = parts.next().ok_or_else(|| DataError::Config {
            field: "datasets",
            value: "none".into(),
            expected: "at least one dataset",
        })?;
        let generators = vec![out.info.generator.clone()];
        out.info.generator = serde_json::Value::Array(generators);
        for (position, part) in parts.enumerate() {
            out.append(part, position + 1)?;
        }
        Ok(out)
    }

    fn append(&mut self, part: Dataset, position: usize) -> Result<(), DataError> {
        let differs = |reason: String| DataError::Format {
            path: PathBuf::from(format!("dataset {position} of the concatenation")),
            reason,
        };
        let shapes = |i: &Info| -> Vec<(String, DType, Vec<usize>)> {
            let f = i.features.iter();
            f.map(|(k, f)| (k.clone(), f.dtype, f.shape.clone()))
                .collect()
        };
        if shapes(&part.info) != shapes(&self.info) || part.info.fps != self.info.fps {
            return Err(differs(format!(
                "features {:?} at {} fps, expected the first dataset's {:?} at {} fps",
                shapes(&part.info),
                part.info.fps,
                shapes(&self.info),
                self.info.fps
            )));
        }
        let (episodes, frames) = (self.info.episodes, self.info.frames);
        for (name, mut values) in part.floats {
            if name == names::EPISODE_INDEX {
                values.iter_mut().for_each(|e| *e += episodes as f32);
            }
            self.floats.entry(name).or_default().extend(values);
        }
        if let (Some(a), Some(b)) = (&mut self.images, part.images) {
            a.extend(b);
        }
        for (name, frames) in part.other_images {
            self.other_images.entry(name).or_default().extend(frames);
        }
        for (name, s) in &part.stats {
            let pooled = match self.stats.get(name) {
                Some(mine) => mine.pooled(s).ok_or_else(|| {
                    differs(format!("statistics of {name:?} of another dimension"))
                })?,
                None => {
                    return Err(differs(format!(
                        "statistics of {name:?}, which the first lacks"
                    )));
                }
            };
            self.stats.insert(name.clone(), pooled);
        }
        self.episodes
            .extend(part.episodes.into_iter().map(|e| EpisodeMeta {
                index: e.index + episodes,
                start: e.start + frames,
                ..e
            }));
        self.info.episodes += part.info.episodes;
        self.info.frames += part.info.frames;
        if let serde_json::Value::Array(g) = &mut self.info.generator {
            g.push(part.info.generator);
        }
        Ok(())
    }

    /// Episode lengths in order (for [`crate::WindowSampler`]).
    pub fn episode_lengths(&self) -> Vec<usize> {
        self.episodes.iter().map(|e| e.length).collect()
    }

    /// A float feature, or an error naming it.
    pub fn feature(&self, name: &str) -> Result<&[f32], DataError> {
        self.floats
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| DataError::Format {
                path: PathBuf::from("info.json"),
                reason: format!("feature {name:?} is not in this dataset"),
            })
    }
}
