//! Filmed episodes, for the paper's Figure 2: one episode run twice from the same seed under
//! the same corruption, changing only the aggregator, drawn side by side.
//!
//! A film is one RGB frame per control step (the state after the step, the executed action
//! drawn as the target marker), each flagged when the newest query covering that step was
//! corrupted. [`side_by_side`] makes the frames of an animation, [`strip`] a still of a few
//! evenly spaced steps. Frames are HWC `u8`, `size x size` pixels per panel.

use mte_policy::ChunkPolicy;
use mte_sim::render::Renderer;

use crate::environment::{EnvError, Environment, Outcome, PushTEnv};
use crate::episode::{EpisodeObserver, QueryEvent, StepEvent};
use crate::pusht::{EpisodeSpec, RolloutError, run_episode_in};
use crate::record::EpisodeRecord;

/// The smallest and largest panel side (px).
pub const PANEL_SIZES: std::ops::RangeInclusive<usize> = 32..=1024;

/// Width of the border that marks a corrupted step (px).
const BORDER: usize = 6;
/// Border colours: a corrupted step, a clean step, after the episode ended.
const CORRUPTED: [u8; 3] = [220, 40, 40];
const CLEAN: [u8; 3] = [235, 235, 235];
const ENDED: [u8; 3] = [110, 110, 110];

/// One control step of a filmed episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Shot {
    /// The frame, `size x size` RGB.
    pub rgb: Vec<u8>,
    /// Whether the newest query covering the step was corrupted.
    pub corrupted: bool,
}

/// A filmed episode.
#[derive(Debug, Clone)]
pub struct Film {
    /// What the runner recorded (the same record as an unfilmed run of the spec).
    pub record: EpisodeRecord,
    /// One shot per control step.
    pub shots: Vec<Shot>,
    /// Panel side (px).
    pub size: usize,
}

/// PushT that draws every state it steps to.
struct Camera {
    env: PushTEnv,
    renderer: Option<Renderer>,
    size: usize,
    frames: Vec<Vec<u8>>,
}

impl Environment for Camera {
    fn action_dim(&self) -> usize {
        self.env.action_dim()
    }
    fn reset(&mut self, seed: u64) -> Result<f64, EnvError> {
        let score = self.env.reset(seed)?;
        self.renderer = Some(Renderer::new(self.env.sim().goal()));
        Ok(score)
    }
    fn observe(
        &mut self,
        needs: mte_policy::ObsNeeds,
    ) -> Result<mte_policy::Observation, EnvError> {
        self.env.observe(needs)
    }
    fn step(&mut self, action: &[f32]) -> Result<Outcome, EnvError> {
        let out = self.env.step(action)?;
        let sim = self.env.sim();
        let target = [f64::from(action[0]), f64::from(action[1])];
        let r = self
            .renderer
            .get_or_insert_with(|| Renderer::new(sim.goal()));
        self.frames.push(r.visualization_with_contacts(
            &sim.scene(),
            sim.contact_segments(),
            Some(target),
            self.size,
            self.size,
        )?);
        Ok(out)
    }
}

/// Which steps' newest query was corrupted.
#[derive(Default)]
struct Marks {
    newest: bool,
    steps: Vec<bool>,
}

impl EpisodeObserver for Marks {
    fn on_query(&mut self, e: &QueryEvent<'_>) {
        self.newest = e.corrupted;
    }
    fn on_step(&mut self, _e: &StepEvent<'_>) {
        self.steps.push(self.newest);
    }
}

/// Runs the episode of `spec` in PushT (reset stream `spec.stream`) and films it at `size`
/// px per side.
pub fn film(
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
    size: usize,
) -> Result<Film, RolloutError> {
    if !PANEL_SIZES.contains(&size) {
        return Err(RolloutError::Config {
            field: "size",
            value: size.to_string(),
            expected: format!("{}..={} px", PANEL_SIZES.start(), PANEL_SIZES.end()),
        });
    }
    let mut cam = Camera {
        env: PushTEnv::new(spec.stream),
        renderer: None,
        size,
        frames: Vec::new(),
    };
    let mut marks = Marks::default();
    let record = run_episode_in(&mut cam, policy, spec, &mut marks)?;
    let shots = cam
        .frames
        .into_iter()
        .zip(marks.steps)
        .map(|(rgb, corrupted)| Shot { rgb, corrupted })
        .collect();
    Ok(Film {
        record,
        shots,
        size,
    })
}

/// Copies a `size x size` frame into `canvas` (`width` px wide) at (`x0`, `y0`) inside a
/// border of `colour`.
fn paste(
    canvas: &mut [u8],
    width: usize,
    (x0, y0): (usize, usize),
    frame: &[u8],
    size: usize,
    colour: [u8; 3],
) {
    let side = size + 2 * BORDER;
    for y in 0..side {
        for x in 0..side {
            let inside =
                (BORDER..BORDER + size).contains(&x) && (BORDER..BORDER + size).contains(&y);
            let px = if inside {
                let i = ((y - BORDER) * size + (x - BORDER)) * 3;
                [frame[i], frame[i + 1], frame[i + 2]]
            } else {
                colour
            };
            let o = ((y0 + y) * width + x0 + x) * 3;
            canvas[o..o + 3].copy_from_slice(&px);
        }
    }
}

/// The shot of `film` at step `k` and its border: the last shot, greyed, once the episode
/// has ended.
fn shot_at(film: &Film, k: usize) -> Option<(&[u8], [u8; 3])> {
    match film.shots.get(k) {
        Some(s) => Some((&s.rgb, if s.corrupted { CORRUPTED } else { CLEAN })),
        None => film.shots.last().map(|s| (s.rgb.as_slice(), ENDED)),
    }
}

/// The frames of a side-by-side animation of `films` (left to right), as long as the
/// longest; `(frames, width, height)`. Corrupted steps have a red border, steps after an
/// episode ended a dark grey one.
pub fn side_by_side(films: &[&Film]) -> (Vec<Vec<u8>>, usize, usize) {
    let size = films.first().map_or(0, |f| f.size);
    let side = size + 2 * BORDER;
    let (width, height) = (side * films.len(), side);
    let len = films.iter().map(|f| f.shots.len()).max().unwrap_or(0);
    let frames = (0..len)
        .map(|k| {
            let mut canvas = vec![255u8; width * height * 3];
            for (i, f) in films.iter().enumerate() {
                if let Some((rgb, colour)) = shot_at(f, k) {
                    paste(&mut canvas, width, (i * side, 0), rgb, size, colour);
                }
            }
            canvas
        })
        .collect();
    (frames, width, height)
}

/// A still of `count` evenly spaced steps (columns), one row per film; `(rgb, width,
/// height)`.
pub fn strip(films: &[&Film], count: usize) -> (Vec<u8>, usize, usize) {
    let size = films.first().map_or(0, |f| f.size);
    let side = size + 2 * BORDER;
    let len = films.iter().map(|f| f.shots.len()).max().unwrap_or(0);
    let count = count.clamp(1, len.max(1));
    let (width, height) = (side * count, side * films.len());
    let mut canvas = vec![255u8; width * height * 3];
    for c in 0..count {
        let k = if count == 1 {
            0
        } else {
            c * (len.saturating_sub(1)) / (count - 1)
        };
        for (r, f) in films.iter().enumerate() {
            if let Some((rgb, colour)) = shot_at(f, k) {
                paste(&mut canvas, width, (c * side, r * side), rgb, size, colour);
            }
        }
    }
    (canvas, width, height)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn film_of(colours: &[(u8, bool)], size: usize) -> Film {
        Film {
            record: EpisodeRecord {
                cell: String::new(),
                arm: "median".into(),
                seed: 0,
                success: false,
                max_coverage: 0.0,
                steps: colours.len(),
                queries: 0,
                corrupted_queries: 0,
                m_counts: Vec::new(),
                q_counts: Vec::new(),
                bracket: None,
                times: crate::record::StageTimes::default(),
                monitors: Default::default(),
            },
            shots: colours
                .iter()
                .map(|&(v, corrupted)| Shot {
                    rgb: vec![v; size * size * 3],
                    corrupted,
                })
                .collect(),
            size,
        }
    }

    #[test]
    fn side_by_side_marks_corrupted_and_ended_steps() {
        let a = film_of(&[(10, false), (20, true), (30, false)], 4);
        let b = film_of(&[(50, false)], 4);
        let (frames, w, h) = side_by_side(&[&a, &b]);
        assert_eq!(
            (frames.len(), w, h),
            (3, 2 * (4 + 2 * BORDER), 4 + 2 * BORDER)
        );
        let px = |f: &[u8], x: usize, y: usize| {
            [
                f[(y * w + x) * 3],
                f[(y * w + x) * 3 + 1],
                f[(y * w + x) * 3 + 2],
            ]
        };
        // Step 1: left panel corrupted (red border), its interior the frame.
        assert_eq!(px(&frames[1], 0, 0), CORRUPTED);
        assert_eq!(px(&frames[1], BORDER, BORDER), [20; 3]);
        // Step 2: the right episode has ended: its last frame, a grey border.
        let right = 4 + 2 * BORDER;
        assert_eq!(px(&frames[2], right, 0), ENDED);
        assert_eq!(px(&frames[2], right + BORDER, BORDER), [50; 3]);
        assert_eq!(px(&frames[0], right, 0), CLEAN);
    }

    #[test]
    fn a_strip_takes_evenly_spaced_steps_one_row_per_film() {
        let a = film_of(
            &[(1, false), (2, false), (3, false), (4, false), (5, false)],
            2,
        );
        let (rgb, w, h) = strip(&[&a, &a], 3);
        let side = 2 + 2 * BORDER;
        assert_eq!((w, h), (3 * side, 2 * side));
        let at = |c: usize, r: usize| rgb[((r * side + BORDER) * w + c * side + BORDER) * 3];
        assert_eq!([at(0, 0), at(1, 0), at(2, 0), at(2, 1)], [1, 3, 5, 5]);
    }
}
