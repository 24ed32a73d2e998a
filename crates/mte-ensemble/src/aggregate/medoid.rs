//! Medoids: the candidate closest (in summed Euclidean distance) to the others.

use super::{Candidates, Workspace};

/// Fills `ws.dist` (n x n, row-major) with Euclidean distances between candidates.
fn pairwise(c: &Candidates<'_>, ws: &mut Workspace) {
    let n = c.len();
    for i in 0..n {
        ws.dist[i * n + i] = 0.0;
        for j in (i + 1)..n {
            let d2: f64 = c
                .row(i)
                .iter()
                .zip(c.row(j))
                .map(|(&a, &b)| {
                    let t = a as f64 - b as f64;
                    t * t
                })
                .sum();
            let dij = d2.sqrt();
            ws.dist[i * n + j] = dij;
            ws.dist[j * n + i] = dij;
        }
    }
}

/// Index of the kept candidate with the smallest distance sum to the other kept ones;
/// ties go to the newest (largest index).
fn medoid_of_kept(n: usize, ws: &Workspace) -> usize {
    let mut best = (f64::INFINITY, 0);
    for i in (0..n).filter(|&i| ws.keep[i]) {
        let s: f64 = (0..n)
            .filter(|&j| ws.keep[j])
            .map(|j| ws.dist[i * n + j])
            .sum();
        if s <= best.0 {
            best = (s, i);
        }
    }
    best.1
}

/// Block medoid.
pub(super) fn block_medoid(c: &Candidates<'_>, ws: &mut Workspace, out: &mut [f32]) {
    trimmed_medoid(c, 0, ws, out);
}

/// Drops the `min(q, n - 1)` candidates with the largest distance sums (ties: the oldest
/// first), then takes the medoid of the rest.
pub(super) fn trimmed_medoid(c: &Candidates<'_>, q: usize, ws: &mut Workspace, out: &mut [f32]) {
    let n = c.len();
    pairwise(c, ws);
    ws.keep[..n].fill(true);
    for i in 0..n {
        ws.score[i] = ws.dist[i * n..(i + 1) * n].iter().sum();
    }
    for _ in 0..q.min(n - 1) {
        let mut worst = (f64::NEG_INFINITY, 0);
        for i in (0..n).filter(|&i| ws.keep[i]) {
            if ws.score[i] > worst.0 {
                worst = (ws.score[i], i);
            }
        }
        ws.keep[worst.1] = false;
    }
    out.copy_from_slice(c.row(medoid_of_kept(n, ws)));
}
