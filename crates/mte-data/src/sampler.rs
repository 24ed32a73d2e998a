//! Diffusion Policy's windowed sampler (`SequenceSampler` with its padding rules).
//!
//! A training sample is a window of `horizon` consecutive frames of one episode. Windows start
//! from `n_obs_steps - 1` frames before the episode's first frame up to `n_action_steps - 1`
//! frames past the last full window; frame indices outside the episode are clamped to its
//! first / last frame (edge padding: the first observation repeated, the last action held),
//! and `pad` marks them. The observation of a sample is its first `n_obs_steps` frames, the
//! action target all `horizon` frames.

use crate::error::DataError;

/// One training window.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Window {
    /// Episode index.
    pub episode: usize,
    /// Global frame index of each of the `horizon` positions (clamped to the episode).
    pub frames: Vec<usize>,
    /// True where the position lies outside the episode (was clamped).
    pub pad: Vec<bool>,
}

/// Enumerates every window of every episode, in order.
#[derive(Clone, Debug)]
pub struct WindowSampler {
    horizon: usize,
    /// (episode, global start of the episode, length, first window offset) per window.
    index: Vec<(usize, usize, usize, isize)>,
}

impl WindowSampler {
    /// `episode_lengths[e]` frames per episode, stored consecutively from frame 0.
    pub fn new(
        episode_lengths: &[usize],
        horizon: usize,
        n_obs_steps: usize,
        n_action_steps: usize,
    ) -> Result<Self, DataError> {
        if horizon == 0 {
            return Err(DataError::Config {
                field: "horizon",
                value: "0".into(),
                expected: "at least 1",
            });
        }
        if n_obs_steps == 0 || n_obs_steps > horizon {
            return Err(DataError::Config {
                field: "n_obs_steps",
                value: n_obs_steps.to_string(),
                expected: "between 1 and the horizon",
            });
        }
        if n_action_steps == 0 || n_action_steps > horizon {
            return Err(DataError::Config {
                field: "n_action_steps",
                value: n_action_steps.to_string(),
                expected: "between 1 and the horizon",
            });
        }
        let pad_before = (n_obs_steps - 1) as isize;
        let pad_after = (n_action_steps - 1) as isize;
        let mut index = Vec::new();
        let mut start = 0usize;
        for (e, &len) in episode_lengths.iter().enumerate() {
            let first = -pad_before;
            let last = len as isize - horizon as isize + pad_after;
            let mut s = first;
            while s <= last {
                index.push((e, start, len, s));
                s += 1;
            }
            start += len;
        }
        Ok(WindowSampler { horizon, index })
    }

    /// Number of windows.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// True when no episode is long enough for a window.
    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }

    /// Window `i` (`None` past the end).
    pub fn window(&self, i: usize) -> Option<Window> {
        let &(episode, start, len, offset) = self.index.get(i)?;
        let mut frames = Vec::with_capacity(self.horizon);
        let mut pad = Vec::with_capacity(self.horizon);
        for k in 0..self.horizon as isize {
            let t = offset + k;
            let clamped = t.clamp(0, len as isize - 1) as usize;
            frames.push(start + clamped);
            pad.push(t < 0 || t >= len as isize);
        }
        Some(Window {
            episode,
            frames,
            pad,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn diffusion_policy_padding() {
        // One episode of 5 frames, horizon 4, 2 observation steps, 3 executed actions:
        // starts from -1 to 5 - 4 + 2 = 3.
        let s = WindowSampler::new(&[5], 4, 2, 3).expect("valid");
        assert_eq!(s.len(), 5);
        let w = s.window(0).expect("first");
        assert_eq!(w.frames, vec![0, 0, 1, 2]);
        assert_eq!(w.pad, vec![true, false, false, false]);
        let w = s.window(4).expect("last");
        assert_eq!(w.frames, vec![3, 4, 4, 4]);
        assert_eq!(w.pad, vec![false, false, true, true]);
        assert!(s.window(5).is_none());
    }

    #[test]
    fn invalid_configs_name_the_field() {
        let e = WindowSampler::new(&[5], 4, 5, 1)
            .expect_err("obs > horizon")
            .to_string();
        assert!(e.contains("n_obs_steps"), "{e}");
        assert!(WindowSampler::new(&[5], 0, 1, 1).is_err());
    }

    proptest! {
        #[test]
        fn windows_stay_inside_their_episode(lens in proptest::collection::vec(1usize..40, 1..6),
                                             horizon in 1usize..20, obs in 1usize..4, act in 1usize..10) {
            prop_assume!(obs <= horizon && act <= horizon);
            let s = WindowSampler::new(&lens, horizon, obs, act).expect("valid");
            let starts: Vec<usize> = lens.iter().scan(0, |acc, &l| { let s = *acc; *acc += l; Some(s) }).collect();
            // Count: per episode max(0, len - horizon + obs + act - 1).
            let expect: usize = lens.iter().map(|&l| (l + obs + act - 1).saturating_sub(horizon)).sum();
            prop_assert_eq!(s.len(), expect);
            for i in 0..s.len() {
                let w = s.window(i).expect("in range");
                let (lo, hi) = (starts[w.episode], starts[w.episode] + lens[w.episode]);
                prop_assert_eq!(w.frames.len(), horizon);
                for f in &w.frames {
                    prop_assert!(*f >= lo && *f < hi);
                }
                // Observation frames are never padded past the end, actions never before the start
                // beyond the observation padding.
                prop_assert!(w.frames.windows(2).all(|p| p[0] <= p[1]));
            }
        }
    }
}
