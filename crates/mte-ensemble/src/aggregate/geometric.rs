//! Geometric median by Weiszfeld's algorithm.

use super::{Candidates, GEOMEDIAN_TOL, MedianTie, Workspace, rank};

/// Geometric median `argmin_y sum_i |x_i - y|_2`, by at most `max_iter` Weiszfeld steps
/// `y <- sum(x_i / r_i) / sum(1 / r_i)`, `r_i = |x_i - y|`, starting from the coordinate-wise
/// median (which is already robust, so outliers far away cost no iterations). Candidates at
/// distance 0 from the estimate are skipped in a step. Stops when a step moves less than
/// `1e-9 * (1 + |y|)`.
pub(super) fn geometric_median(
    c: &Candidates<'_>,
    max_iter: usize,
    ws: &mut Workspace,
    out: &mut [f32],
) {
    let (n, d) = (c.len(), c.dim());
    rank::median(c, MedianTie::Average, ws, out);
    for (y, &o) in ws.acc[..d].iter_mut().zip(out.iter()) {
        *y = o as f64;
    }
    for _ in 0..max_iter {
        ws.acc2[..d].fill(0.0);
        let mut den = 0.0;
        for i in 0..n {
            let r: f64 = c
                .row(i)
                .iter()
                .zip(&ws.acc[..d])
                .map(|(&x, &y)| (x as f64 - y).powi(2))
                .sum::<f64>()
                .sqrt();
            if r > 0.0 {
                den += 1.0 / r;
                for (a, &x) in ws.acc2[..d].iter_mut().zip(c.row(i)) {
                    *a += x as f64 / r;
                }
            }
        }
        if den == 0.0 {
            break; // every candidate coincides with the estimate
        }
        let mut step2 = 0.0;
        let mut norm2 = 0.0;
        for (y, a) in ws.acc[..d].iter_mut().zip(&ws.acc2[..d]) {
            let next = a / den;
            step2 += (next - *y).powi(2);
            norm2 += next * next;
            *y = next;
        }
        if step2.sqrt() <= GEOMEDIAN_TOL * (1.0 + norm2.sqrt()) {
            break;
        }
    }
    for (o, &y) in out.iter_mut().zip(&ws.acc[..d]) {
        *o = y as f32;
    }
}
