//! The defence table: one policy (a defended one, e.g. after encoder adversarial
//! fine-tuning) against another (the undefended original) under the same corruptions, per
//! arm (protocol section 5; paper: Table "metric").
//!
//! Cells pair up by policy, corruption text form and `h`: the defended policy's cell with
//! corruption `c` and stride `h` is compared with the undefended policy's cell with the same
//! `c` and `h`. A trained patch's text form is its directory name, so a patch re-trained
//! against the defended policy (an adaptive attacker) pairs with the undefended policy's
//! patch of the same name from another directory.
//!
//! Per row and arm: the undefended policy's clean coverage, both policies under the
//! corruption, the defended policy's clean coverage (its clean cost), the paired difference
//! over the seeds both ran (Wilcoxon signed-rank), the two-proportion z-test on success
//! (independent arms, as the paper's patch tables), Holm over the rows (Wilcoxon), and the
//! recovered fraction `(defended - undefended) / (clean - undefended)` (the main table's
//! rule: means over the seeds that ran the clean cell and both policies' corrupted cells,
//! with a paired jackknife standard error).

use mte_stats::two_proportion_ztest;
use serde::Serialize;

use super::{
    Block, CellData, CleanRef, Comparison, EpisodeRecord, Recovered, RecoveryEpisodes, ReportError,
    clean_ref, code, compare, delta, denominator, distinct, est, f3, fraction_se, holm_opt, opt_p,
    pct, policy_label, recovered, stats_err, success_count, table,
};
use crate::record::normalise_label;

/// Which two policies the defence table compares (policy paths, compared as lexically
/// normalised paths, or their last path component).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DefencePair {
    /// The policy without the defence.
    pub undefended: String,
    /// The policy with it.
    pub defended: String,
}

/// One corrupted cell pair and arm of the defence table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DefenceRow {
    /// Corruption text form (shared by both cells).
    pub corruption: String,
    /// Query stride.
    pub h: usize,
    /// Arm.
    pub arm: String,
    /// The undefended policy's cell.
    pub undefended_cell: String,
    /// The defended policy's cell.
    pub defended_cell: String,
    /// The undefended policy on its clean cell (same `h`, same arm).
    pub clean: Option<CleanRef>,
    /// The defended policy on its clean cell (same `h`, same arm).
    pub defended_clean: Option<CleanRef>,
    /// Defended (`other`) against undefended (`baseline`) on the seeds both ran.
    pub comparison: Comparison,
    /// Successes and episodes of the undefended policy under the corruption.
    pub undefended_success: (u64, u64),
    /// Successes and episodes of the defended policy under the corruption.
    pub defended_success: (u64, u64),
    /// Two-sided p of the pooled two-proportion z-test on success (`None` without episodes).
    pub ztest_p: Option<f64>,
    /// Holm-adjusted Wilcoxon p over the rows.
    pub holm_wilcoxon: Option<f64>,
    /// Recovered fraction on coverage and success, by the main table's rule (means over the
    /// paired seeds, against the undefended policy's clean cell).
    pub recovered: Recovered,
}

/// The defence table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DefenceTable {
    /// Undefended policy label.
    pub undefended: String,
    /// Defended policy label.
    pub defended: String,
    /// Rows: the defended policy's corrupted cells in manifest order, arms in cell order.
    pub rows: Vec<DefenceRow>,
}

/// Whether `cell` runs the policy the user named: its path, spelled any way that normalises
/// to the same path (`sweeps/../assets/p` and `assets/p`), or its last path component.
fn is_policy(cell: &CellData<'_>, name: &str) -> bool {
    cell.spec.policy_key() == normalise_label(name) || policy_label(&cell.spec.policy) == name
}

/// Builds the table; `arms` are the arms to report (in order), when a cell has them.
pub(super) fn build(
    cells: &[CellData<'_>],
    pair: &DefencePair,
    arms: &[String],
    notes: &mut Vec<String>,
) -> Result<DefenceTable, ReportError> {
    require_policy(cells, "undefended", &pair.undefended)?;
    require_policy(cells, "defended", &pair.defended)?;
    let mut rows = Vec::new();
    for d in cells
        .iter()
        .filter(|c| !c.is_clean() && is_policy(c, &pair.defended))
    {
        let corruption = d.spec.corruption.to_string();
        let Some(u) = find(cells, &pair.undefended, &corruption, d) else {
            notes.push(format!(
                "defence table: no cell of `{}` with corruption {corruption} and h = {} for `{}`",
                pair.undefended, d.spec.h, d.spec.id
            ));
            continue;
        };
        for arm in arms.iter().filter(|a| d.has(a) && u.has(a)) {
            rows.push(row(cells, pair, Compared { u, d }, arm)?);
        }
    }
    let pw: Vec<Option<f64>> = rows.iter().map(|r| r.comparison.wilcoxon_p).collect();
    for (r, h) in rows
        .iter_mut()
        .zip(holm_opt(&pw, "Holm over the defence table (Wilcoxon)")?)
    {
        r.holm_wilcoxon = h;
    }
    Ok(DefenceTable {
        undefended: pair.undefended.clone(),
        defended: pair.defended.clone(),
        rows,
    })
}

/// An error naming the policies the cells have, unless one of them is `name`.
fn require_policy(
    cells: &[CellData<'_>],
    role: &'static str,
    name: &str,
) -> Result<(), ReportError> {
    if cells.iter().any(|c| is_policy(c, name)) {
        return Ok(());
    }
    let available = distinct(cells.iter().map(|c| policy_label(&c.spec.policy)));
    Err(ReportError::UnknownPolicy {
        role,
        policy: name.to_owned(),
        available: available.join(", "),
    })
}

/// The cell of policy `name` with the text form `corruption` at the stride and span of `like`.
fn find<'c, 'a>(
    cells: &'c [CellData<'a>],
    name: &str,
    corruption: &str,
    like: &CellData<'_>,
) -> Option<&'c CellData<'a>> {
    cells.iter().find(|c| {
        is_policy(c, name)
            && c.spec.h == like.spec.h
            && c.spec.span == like.spec.span
            && c.spec.corruption.to_string() == corruption
    })
}

/// The undefended (`u`) and the defended (`d`) policy's cells under one corruption.
#[derive(Clone, Copy)]
struct Compared<'c, 'a> {
    u: &'c CellData<'a>,
    d: &'c CellData<'a>,
}

/// One row: the pair's cells under one arm, with both policies' clean cells beside them.
fn row(
    cells: &[CellData<'_>],
    pair: &DefencePair,
    Compared { u, d }: Compared<'_, '_>,
    arm: &str,
) -> Result<DefenceRow, ReportError> {
    let what = format!("defence `{}` vs `{}`, arm `{arm}`", d.spec.id, u.spec.id);
    let (ue, de) = (u.episodes(arm), d.episodes(arm));
    let comparison = compare(ue, de, arm, &what, d.mcnemar)?;
    let us = (success_count(ue) as u64, ue.len() as u64);
    let ds = (success_count(de) as u64, de.len() as u64);
    let ztest_p = if us.1 > 0 && ds.1 > 0 {
        Some(
            two_proportion_ztest(ds.0, ds.1, us.0, us.1)
                .map_err(stats_err(what))?
                .p_value,
        )
    } else {
        None
    };
    let u_clean = find(cells, &pair.undefended, "clean", d);
    let d_clean = find(cells, &pair.defended, "clean", d);
    let clean = |c: Option<&CellData<'_>>| c.map_or(Ok(None), |c| clean_ref(c, arm));
    let (clean_u, den, clean_d) = (
        clean(u_clean)?,
        denominator(u, u_clean, arm)?,
        clean(d_clean)?,
    );
    let no_eps: &[&EpisodeRecord] = &[];
    let recovered = recovered(
        RecoveryEpisodes {
            clean: u_clean.map_or(no_eps, |c| c.episodes(arm)),
            base: ue,
            other: de,
            other_clean: d_clean.map_or(no_eps, |c| c.episodes(arm)),
        },
        den,
    );
    Ok(DefenceRow {
        corruption: d.spec.corruption.to_string(),
        h: d.spec.h,
        arm: arm.to_owned(),
        undefended_cell: u.spec.id.clone(),
        defended_cell: d.spec.id.clone(),
        clean: clean_u,
        defended_clean: clean_d,
        comparison,
        undefended_success: us,
        defended_success: ds,
        ztest_p,
        holm_wilcoxon: None,
        recovered,
    })
}

impl DefenceTable {
    /// Section 9 of the report.
    pub(super) fn blocks(&self) -> Vec<Block> {
        let mut b = vec![
            Block::Heading(format!(
                "9. Defence: {} against {}",
                code(&self.defended),
                code(&self.undefended)
            )),
            Block::Para(
                "Cells pair by corruption and h (a patch is named by its directory). Mean max \
                 coverage ± standard error per arm; clean: the undefended policy on its clean \
                 cell, clean (def.): the defended one on its own (the defence's clean cost). \
                 Δ = defended − undefended per seed ± paired standard error, p (W): Wilcoxon \
                 signed-rank on paired coverage, Holm over the rows; success: successes / \
                 episodes, p (z): pooled two-proportion z-test. Recovered: (defended − \
                 undefended) / (clean − undefended) on the seeds all three \
                 cells ran, ± its paired jackknife standard error, n/a where undefined."
                    .into(),
            ),
        ];
        if self.rows.is_empty() {
            b.push(Block::Para("No pair of cells matched.".into()));
            return b;
        }
        let fr = |v: Option<f64>| v.map_or_else(|| "n/a".into(), |v| format!("{v:.2}"));
        let rows = self
            .rows
            .iter()
            .map(|r| {
                let c = &r.comparison;
                let sr = |(k, n): (u64, u64)| {
                    if n == 0 {
                        "—".to_string()
                    } else {
                        format!("{k}/{n} ({}%)", pct(k as f64 / n as f64))
                    }
                };
                vec![
                    r.corruption.clone(),
                    r.h.to_string(),
                    code(&r.arm),
                    c.n.to_string(),
                    r.clean
                        .as_ref()
                        .map_or_else(|| "—".into(), |k| f3(k.coverage.mean)),
                    est(c.baseline.as_ref()),
                    est(c.other.as_ref()),
                    r.defended_clean
                        .as_ref()
                        .map_or_else(|| "—".into(), |k| f3(k.coverage.mean)),
                    delta(c.delta.as_ref()),
                    opt_p(c.wilcoxon_p),
                    opt_p(r.holm_wilcoxon),
                    format!("{} → {}", sr(r.undefended_success), sr(r.defended_success)),
                    opt_p(r.ztest_p),
                    fraction_se(&r.recovered),
                    fr(r.recovered.success),
                ]
            })
            .collect();
        b.push(table(
            &[
                "corruption",
                "h",
                "arm",
                "n",
                "clean",
                "undefended",
                "defended",
                "clean (def.)",
                "Δ",
                "p (W)",
                "Holm (W)",
                "success",
                "p (z)",
                "recovered (coverage)",
                "recovered (success)",
            ],
            rows,
        ));
        b
    }
}
