//! The control table: an attack against its control, cell against cell, per arm (the
//! evidence rule "a control for every attack": an adversarial patch beside a grey square of
//! the same size, PGD beside random noise of the same radius).
//!
//! Each pair names two cells of the run (or of runs merged into one report); they are
//! compared per arm on the seeds both ran: mean max coverage of each, the paired difference
//! `attack - control` with its standard error and two-sided Wilcoxon signed-rank p, the
//! McNemar test on paired success (`b`: seeds that succeed under the control only, `c`: under
//! the attack only), and Holm over the rows on each test. A significantly negative Δ says the
//! attack does more than its control; a Δ near zero says the effect is the control's (the
//! size of the perturbation, an occluding square), not the optimisation's.

use serde::Serialize;

use super::{
    Block, CellData, Comparison, ReportError, code, compare, delta, est_rate, holm_both, opt_p,
    table,
};

/// One attack cell and the control cell it is read against (cell ids).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ControlPair {
    /// The attacked cell.
    pub attack: String,
    /// Its control (same schedule, a perturbation without the optimisation).
    pub control: String,
}

/// One pair and arm of the control table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ControlRow {
    /// The attacked cell.
    pub attack_cell: String,
    /// The control cell.
    pub control_cell: String,
    /// Arm.
    pub arm: String,
    /// The attack (`other`) against the control (`baseline`) on the seeds both ran.
    pub comparison: Comparison,
    /// Holm-adjusted Wilcoxon p over the rows.
    pub holm_wilcoxon: Option<f64>,
    /// Holm-adjusted McNemar p over the rows.
    pub holm_mcnemar: Option<f64>,
}

/// The control table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ControlTable {
    /// Rows: pairs in the order given, arms in the attack cell's order.
    pub rows: Vec<ControlRow>,
}

fn cell<'c, 'a>(
    cells: &'c [CellData<'a>],
    id: &str,
    role: &'static str,
) -> Result<&'c CellData<'a>, ReportError> {
    cells
        .iter()
        .find(|c| c.spec.id == id)
        .ok_or_else(|| ReportError::UnknownControlCell {
            role,
            cell: id.to_string(),
            available: cells
                .iter()
                .map(|c| c.spec.id.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        })
}

/// Builds the table; every pair must name cells of the run. Arms both cells ran are
/// compared; a pair with no shared arm is a note.
pub(super) fn build(
    cells: &[CellData<'_>],
    pairs: &[ControlPair],
    notes: &mut Vec<String>,
) -> Result<ControlTable, ReportError> {
    let mut rows = Vec::new();
    for pair in pairs {
        let a = cell(cells, &pair.attack, "attack")?;
        let c = cell(cells, &pair.control, "control")?;
        let before = rows.len();
        for arm in a.arms.iter().filter(|arm| c.has(arm)) {
            let what = format!("control `{}` vs `{}`, arm `{arm}`", a.spec.id, c.spec.id);
            let comparison = compare(c.episodes(arm), a.episodes(arm), arm, &what, a.mcnemar)?;
            rows.push(ControlRow {
                attack_cell: a.spec.id.clone(),
                control_cell: c.spec.id.clone(),
                arm: arm.clone(),
                comparison,
                holm_wilcoxon: None,
                holm_mcnemar: None,
            });
        }
        if rows.len() == before {
            notes.push(format!(
                "control table: `{}` and `{}` share no arm",
                a.spec.id, c.spec.id
            ));
        }
    }
    let comparisons: Vec<Option<&Comparison>> = rows.iter().map(|r| Some(&r.comparison)).collect();
    let adjusted = holm_both(&comparisons, "the control table")?;
    for (r, (w, m)) in rows.iter_mut().zip(adjusted) {
        r.holm_wilcoxon = w;
        r.holm_mcnemar = m;
    }
    Ok(ControlTable { rows })
}

impl ControlTable {
    /// The section, numbered `number`.
    pub(super) fn blocks(&self, number: usize) -> Vec<Block> {
        let mut b = vec![
            Block::Heading(format!("{number}. Attacks against their controls")),
            Block::Para(
                "Each attack cell against the control cell named for it, per arm, on the seeds \
                 both ran: mean max coverage ± standard error (success rate in parentheses), \
                 Δ = attack − control per seed ± paired standard error, p (W): two-sided \
                 Wilcoxon signed-rank on paired coverage; b:c = control-only : attack-only \
                 successes, p (McN): McNemar on paired success; Holm over the rows. A Δ near \
                 zero means the corruption's effect is its control's (its size or its square), \
                 not the attack's optimisation."
                    .into(),
            ),
        ];
        if self.rows.is_empty() {
            b.push(Block::Para("No pair shares an arm.".into()));
            return b;
        }
        let rows = self
            .rows
            .iter()
            .map(|r| {
                let c = &r.comparison;
                vec![
                    code(&r.attack_cell),
                    code(&r.control_cell),
                    code(&r.arm),
                    c.n.to_string(),
                    est_rate(c.baseline.as_ref(), c.baseline_success),
                    est_rate(c.other.as_ref(), c.other_success),
                    delta(c.delta.as_ref()),
                    opt_p(c.wilcoxon_p),
                    opt_p(r.holm_wilcoxon),
                    c.mcnemar
                        .map_or_else(|| "—".into(), |m| format!("{}:{}", m.b, m.c)),
                    opt_p(c.mcnemar.map(|m| m.p_value)),
                    opt_p(r.holm_mcnemar),
                ]
            })
            .collect();
        b.push(table(
            &[
                "attack",
                "control",
                "arm",
                "n",
                "control",
                "attack",
                "Δ",
                "p (W)",
                "Holm (W)",
                "b:c",
                "p (McN)",
                "Holm (McN)",
            ],
            rows,
        ));
        b
    }
}
