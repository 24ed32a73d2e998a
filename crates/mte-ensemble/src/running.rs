//! Running sums per control time for the weighted means ([`RunningWeights`]): what lets a
//! [`TemporalEnsembler`](crate::TemporalEnsembler) serve `ewm` and `mean` without gathering
//! the candidates.
//!
//! A chunk queried at `t` with `span` executable rows is a candidate for the control times
//! `t .. t + span`. Inserting it adds `w_k x` to the sum of each of those times, `k` being the
//! number of finite candidates that time already has: chunks arrive in query order, so `k` is
//! the candidate's position oldest first, the position the gathered mean weighs it by. Each
//! sum is `Σ w_k x_k` and `Σ w_k` in f64, added in candidate order from zero with the same
//! operations as `weighted_mean`, so the quotient has the gathered mean's bits.
//!
//! The sums live in a ring of `slots` control times (slot `tau mod slots`, tagged with `tau`).
//! A slot is claimed by the first chunk that covers its time and cleared then. With `slots`
//! at least `span`, a slot tagged `tau` has seen every chunk covering `tau` inserted since it
//! was claimed: a chunk that takes the slot for another time comes after every chunk covering
//! `tau` (its own query time is later than `tau` or its rows end before `tau`), so `tau`
//! cannot be claimed again. A time whose slot was taken (possible only for chunks inserted
//! far apart before the first action) has no sums, and the ensembler gathers instead.

use crate::aggregate::{RunningWeights, Workspace};

/// The tag of a slot that holds no control time.
const EMPTY: u64 = u64::MAX;

/// The counts of one control time (its sums are in [`RunningSums`]'s `acc`). How many chunks
/// cover the time, and how many of them are corrupted, the ensembler reads from its ring of
/// chunks at the step; per row, only what the weights need is counted here.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TimeSums {
    /// The control time these sums are for ([`EMPTY`] for none).
    pub tau: u64,
    /// Finite candidates (summed).
    pub used: u32,
    /// Non-finite candidates (not summed).
    pub excluded: u32,
    /// Of those, from chunks flagged corrupted.
    pub excluded_corrupted: u32,
}

impl TimeSums {
    const EMPTY: Self = Self::claimed(EMPTY);

    /// The slot of `tau` with no candidate yet.
    const fn claimed(tau: u64) -> Self {
        Self {
            tau,
            used: 0,
            excluded: 0,
            excluded_corrupted: 0,
        }
    }
}

/// The ring of per-time sums (see the module documentation).
#[derive(Debug, Clone)]
pub(crate) struct RunningSums {
    dim: usize,
    /// `w_k` for `k < span`, the aggregator's own weights.
    weights: Vec<f64>,
    /// `totals[n] = w_0 + ... + w_{n-1}`, added in that order from zero (as
    /// `weighted_mean`'s callers sum them), for `n <= span`.
    totals: Vec<f64>,
    times: Vec<TimeSums>,
    /// `slots * dim` weighted sums, slot-major.
    acc: Vec<f64>,
}

impl RunningSums {
    /// Sums for `slots` (`>= span`) control times of `dim` coordinates, weighing the `k`-th
    /// finite candidate of a time by `r`'s `w_k`, as `ws` does.
    pub fn new(
        r: RunningWeights,
        span: usize,
        slots: usize,
        dim: usize,
        ws: &mut Workspace,
    ) -> Self {
        debug_assert!(slots >= span && ws.capacity() >= span);
        let mut weights = vec![0.0; span];
        ws.running_weights_into(r, &mut weights);
        let totals = std::iter::once(0.0)
            .chain(weights.iter().scan(0.0, |t, &w| {
                *t += w;
                Some(*t)
            }))
            .collect();
        Self {
            dim,
            weights,
            totals,
            times: vec![TimeSums::EMPTY; slots],
            acc: vec![0.0; slots * dim],
        }
    }

    /// Forgets every time (a new episode). Does not allocate.
    pub fn clear(&mut self) {
        self.times.fill(TimeSums::EMPTY);
    }

    /// The counts of `tau`, the sum of its weights and its `d` weighted sums, if this ring
    /// holds `tau`.
    pub fn get(&self, tau: u64) -> Option<(&TimeSums, f64, &[f64])> {
        let i = (tau % self.times.len() as u64) as usize;
        let s = &self.times[i];
        (s.tau == tau).then(|| {
            let sums = &self.acc[i * self.dim..(i + 1) * self.dim];
            (s, self.totals[s.used as usize], sums)
        })
    }

    /// Adds the chunk queried at `t_query`: `rows` holds its `span` executable rows of `d`
    /// values (row `e` is the candidate for time `t_query + e`); `row_finite` says which rows
    /// are finite when not all are.
    pub fn add_chunk(
        &mut self,
        t_query: u64,
        rows: &[f32],
        corrupted: bool,
        row_finite: Option<&[bool]>,
    ) {
        let chunk = Chunk {
            t_query,
            rows,
            corrupted,
            row_finite,
        };
        let (times, acc, w) = (&mut self.times[..], &mut self.acc[..], &self.weights[..]);
        match self.dim {
            2 => add_chunk::<2>(times, acc, w, &chunk),
            7 => add_chunk::<7>(times, acc, w, &chunk),
            14 => add_chunk::<14>(times, acc, w, &chunk),
            d => add_rows(times, acc, w, &chunk, d),
        }
    }
}

/// One inserted chunk, as [`RunningSums::add_chunk`] takes it.
struct Chunk<'a> {
    t_query: u64,
    rows: &'a [f32],
    corrupted: bool,
    row_finite: Option<&'a [bool]>,
}

/// [`add_rows`] with the dimension `D` a constant, so that a row's sum is whole registers;
/// compiled for AVX-512, AVX2 and the baseline.
#[cfg_attr(
    not(feature = "cap-avx2"),
    multiversion::multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2", "aarch64+neon"))
)]
#[cfg_attr(
    feature = "cap-avx2",
    multiversion::multiversion(targets("x86_64+avx2", "aarch64+neon"))
)]
fn add_chunk<const D: usize>(times: &mut [TimeSums], acc: &mut [f64], w: &[f64], c: &Chunk<'_>) {
    add_rows(times, acc, w, c, D);
}

/// Adds each row of `c` to its time's sums (`d` coordinates per row).
#[inline(always)]
fn add_rows(times: &mut [TimeSums], acc: &mut [f64], w: &[f64], c: &Chunk<'_>, d: usize) {
    let n = times.len();
    let mut i = (c.t_query % n as u64) as usize;
    for (e, row) in c.rows.chunks_exact(d).enumerate() {
        let tau = c.t_query + e as u64;
        let (s, sum) = (&mut times[i], &mut acc[i * d..(i + 1) * d]);
        if s.tau != tau {
            *s = TimeSums::claimed(tau);
            sum.fill(0.0);
        }
        if c.row_finite.is_none_or(|f| f[e]) {
            let wk = w[s.used as usize];
            // `weighted_mean`'s operations, in its order: a product, then a sum.
            for (a, &x) in sum.iter_mut().zip(row) {
                *a += wk * f64::from(x);
            }
            s.used += 1;
        } else {
            s.excluded += 1;
            s.excluded_corrupted += u32::from(c.corrupted);
        }
        i += 1;
        if i == n {
            i = 0;
        }
    }
}
