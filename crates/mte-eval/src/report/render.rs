//! Rendering of a [`Report`]: its blocks (one function per section), Markdown and
//! self-contained HTML, and the formatting helpers every table shares. The computation is
//! in the parent module; nothing here computes a statistic.

use super::*;

/// Coverage-like values: three decimals, no negative zero.
pub(super) fn f3(x: f64) -> String {
    let s = format!("{x:.3}");
    if s == "-0.000" { "0.000".into() } else { s }
}

/// Signed, three decimals.
pub(super) fn s3(x: f64) -> String {
    let s = format!("{x:+.3}");
    if s == "-0.000" { "+0.000".into() } else { s }
}

/// A percentage with one decimal (`x` in `[0, 1]`).
pub(super) fn pct(x: f64) -> String {
    let s = format!("{:.1}", 100.0 * x);
    if s == "-0.0" { "0.0".into() } else { s }
}

/// A p-value with two significant digits, in scientific form below `1e-3`.
pub(super) fn fmt_p(p: f64) -> String {
    if p.is_nan() {
        return "n/a".into();
    }
    if p <= 0.0 {
        return "< 1e-300".into();
    }
    if p < 1e-3 {
        return format!("{p:.1e}");
    }
    let decimals = (1 - p.log10().floor() as i32).max(1) as usize;
    format!("{p:.decimals$}")
}

pub(super) fn opt_p(p: Option<f64>) -> String {
    p.map_or_else(|| "n/a".into(), fmt_p)
}

pub(super) fn est(e: Option<&Estimate>) -> String {
    match e {
        Some(Estimate {
            mean, se: Some(se), ..
        }) => format!("{} ± {}", f3(*mean), f3(*se)),
        Some(Estimate { mean, se: None, .. }) => f3(*mean),
        None => "—".into(),
    }
}

/// An estimate with its success rate in parentheses, when there is one.
pub(super) fn est_rate(e: Option<&Estimate>, success: Option<f64>) -> String {
    match success {
        Some(s) => format!("{} ({}%)", est(e), pct(s)),
        None => est(e),
    }
}

pub(super) fn delta(e: Option<&Estimate>) -> String {
    match e {
        Some(Estimate {
            mean, se: Some(se), ..
        }) => format!("{} ± {}", s3(*mean), f3(*se)),
        Some(Estimate { mean, se: None, .. }) => s3(*mean),
        None => "—".into(),
    }
}

pub(super) fn code(s: &str) -> String {
    format!("`{s}`")
}

/// A block of the document; Markdown and HTML render the same blocks.
pub(super) enum Block {
    Title(String),
    Heading(String),
    Para(String),
    Bullets(Vec<String>),
    Table {
        head: Vec<String>,
        rows: Vec<Vec<String>>,
    },
    Plots,
    /// An image file beside the report: (alt text, relative path).
    Image(String, String),
}

pub(super) fn table(head: &[&str], rows: Vec<Vec<String>>) -> Block {
    Block::Table {
        head: head.iter().map(|s| s.to_string()).collect(),
        rows,
    }
}

/// How the report names its McNemar test.
fn mcnemar_name(t: mte_stats::McNemarTest) -> &'static str {
    match t {
        mte_stats::McNemarTest::Exact => "exact McNemar test",
        mte_stats::McNemarTest::Chi2Corrected => {
            "McNemar's chi-square test with continuity correction"
        }
    }
}

/// The main table's Holm sentence: it counts the rows each family of tests adjusts over,
/// the rows that have that test, not every row (a cell with no records, or without both
/// arms, has no test and is left out of the adjustment).
fn holm_rows_sentence(rows: &[MainRow]) -> String {
    let w = rows.iter().filter(|r| r.holm_wilcoxon.is_some()).count();
    let m = rows.iter().filter(|r| r.holm_mcnemar.is_some()).count();
    let of = |k: usize| {
        if k == rows.len() {
            format!("the {k} rows")
        } else {
            format!("the {k} of {} rows that have the test", rows.len())
        }
    };
    if w == m {
        format!("Holm over {} (each test separately).", of(w))
    } else {
        format!("Holm over {} (Wilcoxon) and {} (McNemar).", of(w), of(m))
    }
}

/// A clean reference as `coverage (success%)`, or a dash.
pub(super) fn clean_cell_text(k: Option<&CleanRef>) -> String {
    k.map_or_else(
        || "—".into(),
        |k| format!("{} ({}%)", f3(k.coverage.mean), pct(k.success)),
    )
}

/// The report's machine line: records are bit-identical only on one CPU model.
pub(super) fn machine_line(machines: &[String]) -> String {
    match machines {
        [] => "machine: not recorded (run written before manifests named their machine)".into(),
        [one] => format!("machine: {one}"),
        many => format!(
            "machines ({}; records from different CPUs are not bit-identical, see the README's \
             Reproducibility): {}",
            many.len(),
            many.join("; ")
        ),
    }
}

impl Report {
    /// The report as blocks: the header, then one section per function, in order.
    fn blocks(&self) -> Vec<Block> {
        let mut b = Vec::new();
        self.header(&mut b);
        self.main_table(&mut b);
        self.aggregators(&mut b);
        self.bracket(&mut b);
        self.recovered(&mut b);
        self.coverage_counts(&mut b);
        self.overhead(&mut b);
        self.failures(&mut b);
        self.plots_section(&mut b);
        self.defence_section(&mut b);
        self.control_section(&mut b);
        self.clean_section(&mut b);
        b
    }

    /// The title and the run's metadata.
    fn header(&self, b: &mut Vec<Block>) {
        let m = &self.manifest;
        b.push(Block::Title(format!("Evaluation report: {}", self.name)));
        let mut meta = vec![
            format!(
                "run format {}, mte {}, commit {}, created {} (Unix s), noise seed {}",
                code(&m.format),
                m.mte_version,
                m.git_commit
                    .as_deref()
                    .map_or_else(|| "unknown".into(), code),
                m.created_unix_s,
                m.noise_seed
            ),
            format!(
                "{} cells ({} corrupted), {} episode records, {} failure record(s)",
                self.cells,
                self.corrupted_cells,
                self.episodes,
                self.failures.len()
            ),
            format!(
                "baseline arm {}, robust arm {}",
                code(&self.baseline),
                code(&self.robust)
            ),
            machine_line(&m.machines),
        ];
        meta.extend(self.notes.iter().cloned());
        b.push(Block::Bullets(meta));
    }

    /// Section 1: the main table.
    fn main_table(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading(format!(
            "1. Main table: {} against {}",
            code(&self.robust),
            code(&self.baseline)
        )));
        b.push(Block::Para(format!(
            "One row per corrupted cell. Mean max coverage ± standard error over the seeds both \
             arms ran (n), success rate in parentheses; clean: the baseline and the robust arm on \
             the clean cell of the same policy and h (a gap between them on clean data is a \
             confound of every comparison below); clean Δ (p): robust − baseline on that clean \
             cell per seed and its two-sided paired Wilcoxon p. Δ = robust − baseline per seed, \
             ± paired standard error. \
             p (W): two-sided Wilcoxon signed-rank test on paired max coverage; p (McN): {} \
             on paired success, b:c = baseline-only : robust-only successes. {}",
            mcnemar_name(self.mcnemar),
            holm_rows_sentence(&self.main)
        )));
        if self.main.is_empty() {
            b.push(Block::Para("No corrupted cell.".into()));
        } else {
            let rows = self
                .main
                .iter()
                .map(|r| {
                    let c = r.comparison.as_ref();
                    vec![
                        code(&r.cell),
                        r.corruption.clone(),
                        r.q.to_string(),
                        r.h.to_string(),
                        c.map_or_else(|| "0".into(), |c| c.n.to_string()),
                        clean_cell_text(r.clean.as_ref()),
                        clean_cell_text(r.robust_clean.as_ref()),
                        r.clean_comparison.as_ref().map_or_else(
                            || "—".into(),
                            |k| format!("{} ({})", delta(k.delta.as_ref()), opt_p(k.wilcoxon_p)),
                        ),
                        est_rate(
                            c.and_then(|c| c.baseline.as_ref()),
                            c.and_then(|c| c.baseline_success),
                        ),
                        est_rate(
                            c.and_then(|c| c.other.as_ref()),
                            c.and_then(|c| c.other_success),
                        ),
                        delta(c.and_then(|c| c.delta.as_ref())),
                        opt_p(c.and_then(|c| c.wilcoxon_p)),
                        opt_p(r.holm_wilcoxon),
                        c.and_then(|c| c.mcnemar)
                            .map_or_else(|| "—".into(), |m| format!("{}:{}", m.b, m.c)),
                        opt_p(c.and_then(|c| c.mcnemar.map(|m| m.p_value))),
                        opt_p(r.holm_mcnemar),
                    ]
                })
                .collect();
            b.push(table(
                &[
                    "cell",
                    "corruption",
                    "q",
                    "h",
                    "n",
                    "clean (baseline)",
                    "clean (robust)",
                    "clean Δ (p)",
                    "baseline",
                    "robust",
                    "Δ",
                    "p (W)",
                    "Holm (W)",
                    "b:c",
                    "p (McN)",
                    "Holm (McN)",
                ],
                rows,
            ));
        }
    }

    /// Section 2: the aggregators on the focus cell.
    fn aggregators(&self, b: &mut Vec<Block>) {
        let f = &self.focus;
        b.push(Block::Heading(format!(
            "2. Aggregators on {} ({})",
            code(&f.cell),
            f.corruption
        )));
        b.push(Block::Para(format!(
            "Every arm of the cell: success rate with its Wilson {}% interval and mean max \
             coverage ± standard error over the arm's episodes; against {} on the seeds both \
             ran: Δ ± paired standard error, Wilcoxon and McNemar p-values, Holm over the arms.",
            (CONFIDENCE * 100.0).round(),
            code(&self.baseline)
        )));
        b.push(arms_table(f));
    }

    /// The last section (9, after the optional defence and control tables): every clean
    /// cell, every arm against the baseline.
    fn clean_section(&self, b: &mut Vec<Block>) {
        let number = 9 + usize::from(self.defence.is_some()) + usize::from(self.controls.is_some());
        b.push(Block::Heading(format!(
            "{number}. Clean cells: every arm against the baseline"
        )));
        b.push(Block::Para(format!(
            "The clean-data differences between arms, which every comparison under corruption \
             of the same policy and h carries (columns as in section 2, against {}).",
            code(&self.baseline)
        )));
        if self.clean_cells.is_empty() {
            b.push(Block::Para("No clean cell.".into()));
        }
        for f in &self.clean_cells {
            b.push(Block::Para(format!("Cell {}:", code(&f.cell))));
            b.push(arms_table(f));
        }
    }
}

/// The arms of one cell against the baseline (sections 2 and 10).
fn arms_table(f: &FocusTable) -> Block {
    {
        let rows = f
            .rows
            .iter()
            .map(|r| {
                let c = r.vs_baseline.as_ref();
                vec![
                    code(&r.arm),
                    r.n.to_string(),
                    match r.success_ci {
                        Some((lo, hi)) => format!(
                            "{} [{}, {}]",
                            pct(r.successes as f64 / r.n as f64),
                            pct(lo),
                            pct(hi)
                        ),
                        None => "—".into(),
                    },
                    est(r.coverage.as_ref()),
                    c.map_or_else(|| "—".into(), |c| c.n.to_string()),
                    delta(c.and_then(|c| c.delta.as_ref())),
                    c.map_or_else(|| "—".into(), |c| opt_p(c.wilcoxon_p)),
                    c.map_or_else(|| "—".into(), |_| opt_p(r.holm_wilcoxon)),
                    c.map_or_else(|| "—".into(), |c| opt_p(c.mcnemar.map(|m| m.p_value))),
                    c.map_or_else(|| "—".into(), |_| opt_p(r.holm_mcnemar)),
                ]
            })
            .collect();
        table(
            &[
                "arm",
                "n",
                "success % [95% CI]",
                "coverage",
                "pairs",
                "Δ vs baseline",
                "p (W)",
                "Holm (W)",
                "p (McN)",
                "Holm (McN)",
            ],
            rows,
        )
    }
}

/// Columns of a bracket table row (section 3), after the optional cell column.
const BRACKET_HEAD: [&str; 11] = [
    "arm",
    "episodes",
    "regime",
    "steps",
    "outside %",
    "median excess",
    "max excess",
    "zero-width outside",
    "coincide %",
    "nearest median",
    "nearest p99",
];

/// One arm's rows of a bracket table, one per regime (a dash row when the arm never had a
/// corrupted candidate), prefixed by the cell's id in the per-cell table.
fn bracket_rows(cell: Option<&str>, a: &ArmBrackets) -> Vec<Vec<String>> {
    let dash = || "—".to_string();
    let opt = |v: Option<f64>| v.map_or_else(dash, f3);
    let body = |r: Option<&BracketRow>| -> Vec<String> {
        let Some(r) = r else {
            let mut row = vec![dash(), "0".into()];
            row.extend(std::iter::repeat_with(dash).take(7));
            return row;
        };
        vec![
            code(&r.regime.to_string()),
            r.steps.to_string(),
            format!("{:.1}", r.outside_pct),
            f3(r.median_excess),
            f3(r.max_excess),
            r.zero_width_outside.to_string(),
            format!("{:.1}", r.coincide_pct),
            opt(r.nearest_median),
            opt(r.nearest_p99),
        ]
    };
    let regimes: Vec<Option<&BracketRow>> = if a.rows.is_empty() {
        vec![None]
    } else {
        a.rows.iter().map(Some).collect()
    };
    regimes
        .into_iter()
        .map(|r| {
            let mut row: Vec<String> = cell.map(code).into_iter().collect();
            row.extend([code(&a.arm), a.episodes.to_string()]);
            row.extend(body(r));
            row
        })
        .collect()
}

impl Report {
    /// Section 3: bracket diagnostics by regime.
    fn bracket(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("3. Bracket diagnostics by regime".into()));
        b.push(Block::Para(
            "Control steps with at least one corrupted candidate, over the corrupted cells, \
             grouped by regime: share whose output left the clean bracket, excess beyond it in \
             bracket widths, steps with an excursion on a zero-width coordinate, share \
             coinciding with a candidate, and nearest-candidate distance over mean pairwise \
             distance. Max excess is the largest over steps and has no bound where a \
             coordinate's bracket is nearly zero wide; the median excess is the figure to \
             compare."
                .into(),
        ));
        if self.brackets.is_empty() {
            b.push(Block::Para("No bracket data.".into()));
        } else {
            let rows = self
                .brackets
                .iter()
                .flat_map(|a| bracket_rows(None, a))
                .collect();
            b.push(table(&BRACKET_HEAD, rows));
        }
        self.cell_brackets(b);
    }

    /// Section 3, per corrupted cell (runs with several): the pooled table mixes corruptions
    /// of different strength.
    fn cell_brackets(&self, b: &mut Vec<Block>) {
        if self.cell_brackets.is_empty() {
            return;
        }
        b.push(Block::Para("The same per corrupted cell:".into()));
        let rows = self
            .cell_brackets
            .iter()
            .flat_map(|c| {
                c.arms
                    .iter()
                    .flat_map(|a| bracket_rows(Some(c.cell.as_str()), a))
            })
            .collect();
        let head: Vec<&str> = std::iter::once("cell").chain(BRACKET_HEAD).collect();
        b.push(table(&head, rows));
    }

    /// Section 4: the recovered fraction.
    fn recovered(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("4. Recovered fraction".into()));
        b.push(Block::Para(format!(
            "(robust − baseline) / (clean − baseline) on mean max coverage and on success rate, \
             on the seeds that ran the clean cell and both arms under the corruption, ± its \
             paired jackknife standard error (leave one seed out): \
             1 restores the clean baseline, 0 does nothing. n/a where undefined, and where the \
             denominator is not significantly above zero (the corruption does not lower the \
             baseline: paired Wilcoxon on coverage, {} on success, p < 0.05 over \
             the seeds both cells ran), since a fraction of noise is not meaningful. \
             Against own clean: 1 − (robust clean − robust) / (clean − baseline), the share of \
             the baseline's loss that the robust arm avoids measured from its own clean value, \
             so a clean-data gap between the arms is not counted as recovery. \
             Baseline {}, robust {}.",
            mcnemar_name(self.mcnemar),
            code(&self.baseline),
            code(&self.robust)
        )));
        let mut reasons = Vec::new();
        let rows = self
            .main
            .iter()
            .map(|r| {
                let c = r.comparison.as_ref();
                if let Some(n) = &r.recovered.note {
                    reasons.push(format!("{}: {n}", code(&r.cell)));
                }
                if let Some(n) = partial_seeds(&r.recovered, c.map_or(0, |c| c.n)) {
                    reasons.push(format!("{}: {n}", code(&r.cell)));
                }
                let fr = |v: Option<f64>| v.map_or_else(|| "n/a".into(), |v| format!("{v:.2}"));
                vec![
                    code(&r.cell),
                    r.clean
                        .as_ref()
                        .map_or_else(|| "—".into(), |k| f3(k.coverage.mean)),
                    c.and_then(|c| c.baseline)
                        .map_or_else(|| "—".into(), |e| f3(e.mean)),
                    c.and_then(|c| c.other)
                        .map_or_else(|| "—".into(), |e| f3(e.mean)),
                    r.robust_clean
                        .as_ref()
                        .map_or_else(|| "—".into(), |k| f3(k.coverage.mean)),
                    fraction_se(&r.recovered),
                    own_se(&r.recovered),
                    fr(r.recovered.success),
                ]
            })
            .collect();
        b.push(table(
            &[
                "cell",
                "clean",
                "baseline",
                "robust",
                "robust clean",
                "recovered (coverage)",
                "against own clean",
                "recovered (success)",
            ],
            rows,
        ));
        if !reasons.is_empty() {
            b.push(Block::Bullets(reasons));
        }
    }

    /// Section 5: the distribution of M(τ) and q(τ).
    fn coverage_counts(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("5. Distribution of M(τ) and q(τ)".into()));
        b.push(Block::Para(
            "Share of control steps (%) by the number of covering chunks M and by the measured \
             number of corrupted ones q, per ensemble arm, over the corrupted cells."
                .into(),
        ));
        if self.distributions.is_empty() {
            b.push(Block::Para("No data.".into()));
        } else {
            for (name, get) in [
                (
                    "M",
                    (|d: &Distribution| &d.m) as fn(&Distribution) -> &Vec<u64>,
                ),
                ("q", |d: &Distribution| &d.q),
            ] {
                let width = self
                    .distributions
                    .iter()
                    .map(|d| get(d).len())
                    .max()
                    .unwrap_or(0);
                let cols: Vec<usize> = (0..width)
                    .filter(|&k| {
                        self.distributions
                            .iter()
                            .any(|d| get(d).get(k).is_some_and(|&v| v > 0))
                    })
                    .collect();
                let mut head = vec!["arm".to_string(), "steps".to_string()];
                head.extend(cols.iter().map(|k| format!("{name}={k}")));
                let rows = self
                    .distributions
                    .iter()
                    .map(|d| {
                        let v = get(d);
                        let total: u64 = v.iter().sum();
                        let mut row = vec![code(&d.arm), total.to_string()];
                        row.extend(cols.iter().map(|&k| {
                            let x = v.get(k).copied().unwrap_or(0);
                            if total == 0 {
                                "—".into()
                            } else {
                                pct(x as f64 / total as f64)
                            }
                        }));
                        row
                    })
                    .collect();
                b.push(Block::Table { head, rows });
            }
        }
    }

    /// Section 6: runner overhead.
    fn overhead(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("6. Runner overhead".into()));
        b.push(Block::Para(
            "Share of the total wall time by stage (%), over all cells; runner = total − policy \
             − simulator − render − corruption (ensembler included; ensemble: the ensembler \
             alone), and the runner's time per control step."
                .into(),
        ));
        let rows = self
            .overhead
            .iter()
            .map(|o| {
                let t = &o.times;
                let share = |x: f64| {
                    if t.total_s > 0.0 {
                        pct(x / t.total_s)
                    } else {
                        "—".into()
                    }
                };
                vec![
                    code(&o.arm),
                    o.episodes.to_string(),
                    o.steps.to_string(),
                    format!("{:.1}", t.total_s),
                    share(t.policy_s),
                    share(t.sim_s),
                    share(t.render_s),
                    share(t.corruption_s),
                    share(o.runner_s),
                    share(t.ensemble_s),
                    o.us_per_step()
                        .map_or_else(|| "—".into(), |u| format!("{u:.1}")),
                ]
            })
            .collect();
        b.push(table(
            &[
                "arm",
                "episodes",
                "steps",
                "total s",
                "policy %",
                "sim %",
                "render %",
                "corruption %",
                "runner %",
                "ensemble %",
                "runner µs/step",
            ],
            rows,
        ));
    }

    /// Section 7: failures.
    fn failures(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("7. Failures".into()));
        if self.failures.is_empty() {
            b.push(Block::Para("None.".into()));
        } else {
            let rows = self
                .failures
                .iter()
                .map(|e| {
                    vec![
                        code(&e.cell),
                        e.arm.as_deref().map_or_else(|| "—".into(), code),
                        e.seed.map_or_else(|| "—".into(), |s| s.to_string()),
                        e.error.clone(),
                    ]
                })
                .collect();
            b.push(table(&["cell", "arm", "seed", "error"], rows));
        }
    }

    /// Section 8: plots.
    fn plots_section(&self, b: &mut Vec<Block>) {
        b.push(Block::Heading("8. Plots".into()));
        if self.plots.is_empty() {
            b.push(Block::Para("No plot (no corrupted cell).".into()));
        } else {
            b.push(Block::Plots);
        }
        self.figure2_blocks(b);
    }

    /// Figure 2: one episode under the same corruption, baseline beside robust arm.
    fn figure2_blocks(&self, b: &mut Vec<Block>) {
        let Some(f) = &self.figure2 else {
            if !self.main.is_empty() {
                b.push(Block::Para(format!(
                    "Figure 2: no paired episode of a corrupted cell that {} solves and {} does \
                     not.",
                    code(&self.robust),
                    code(&self.baseline)
                )));
            }
            return;
        };
        let cov = |(s, c): (bool, f64)| {
            format!(
                "max coverage {c:.3}, {}",
                if s { "success" } else { "failure" }
            )
        };
        b.push(Block::Para(format!(
            "Figure 2: cell {}, seed {}: the same episode (same reset, same sampling noise, same \
             corruption schedule) run with {} (left, {}) and {} (right, {}). A red border marks a \
             step whose newest query was corrupted; the cross is the executed action (target); a \
             grey border, an episode that has ended.{}",
            code(&f.cell),
            f.seed,
            code(&self.baseline),
            cov(f.baseline),
            code(&self.robust),
            cov(f.robust),
            if f.files.is_empty() {
                format!(
                    " Not rendered: `mte report --figure2` films it (or `mte film --policy {} --seed {} ...`).",
                    f.policy, f.seed
                )
            } else {
                String::new()
            }
        )));
        for (alt, path) in &f.files {
            b.push(Block::Image(alt.clone(), path.clone()));
        }
    }

    /// Section 9 (when asked for): the defence table.
    fn defence_section(&self, b: &mut Vec<Block>) {
        if let Some(t) = &self.defence {
            b.extend(t.blocks());
        }
    }

    /// Section 9 or 10 (when asked for): attacks against their controls.
    fn control_section(&self, b: &mut Vec<Block>) {
        if let Some(t) = &self.controls {
            b.extend(t.blocks(9 + usize::from(self.defence.is_some())));
        }
    }

    /// The report as GitHub-flavoured Markdown (plots linked as `plots/<name>.svg`).
    pub fn markdown(&self) -> String {
        let mut out = String::new();
        for block in self.blocks() {
            match block {
                Block::Title(t) => {
                    let _ = writeln!(out, "# {t}");
                }
                Block::Heading(t) => {
                    let _ = writeln!(out, "## {t}");
                }
                Block::Para(t) => {
                    let _ = writeln!(out, "{t}");
                }
                Block::Bullets(items) => {
                    for i in items {
                        let _ = writeln!(out, "- {}", md_inline(&i));
                    }
                }
                Block::Table { head, rows } => {
                    let line = |cells: &[String]| {
                        let cells: Vec<String> = cells.iter().map(|c| md_cell(c)).collect();
                        format!("| {} |", cells.join(" | "))
                    };
                    let _ = writeln!(out, "{}", line(&head));
                    let rule: Vec<&str> = head
                        .iter()
                        .map(|h| if is_text(h) { ":--" } else { "--:" })
                        .collect();
                    let _ = writeln!(out, "|{}|", rule.join("|"));
                    for r in &rows {
                        let _ = writeln!(out, "{}", line(r));
                    }
                }
                Block::Plots => {
                    for p in &self.plots {
                        let _ = writeln!(out, "![{}](plots/{}.svg)", p.title, p.name);
                    }
                }
                Block::Image(alt, path) => {
                    let _ = writeln!(out, "![{alt}]({path})");
                }
            }
            out.push('\n');
        }
        while out.ends_with("\n\n") {
            out.pop();
        }
        out
    }

    /// The report as one self-contained HTML page (plots inlined as SVG, no external
    /// asset).
    pub fn html(&self) -> String {
        let mut out = String::new();
        out.push_str("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
        let _ = writeln!(out, "<title>mte report: {}</title>", esc(&self.name));
        out.push_str(concat!(
            "<style>\n",
            "body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:80em;",
            "margin:2em auto;padding:0 1em;color:#222;line-height:1.45}\n",
            "h1{font-size:1.6em}h2{font-size:1.25em;margin-top:2em;border-bottom:1px solid #ddd}\n",
            "table{border-collapse:collapse;margin:.8em 0;font-size:.88em}\n",
            "th,td{border:1px solid #d0d0d0;padding:.25em .6em;text-align:right;",
            "font-variant-numeric:tabular-nums}\n",
            "th{background:#f2f2f2}th.t,td.t{text-align:left}\n",
            "tr:nth-child(even) td{background:#fafafa}\n",
            "code{background:#f2f2f2;padding:0 .25em;border-radius:3px;font-size:.95em}\n",
            "figure{display:inline-block;margin:.5em;vertical-align:top}\n",
            "figure svg{max-width:100%;height:auto}\n",
            "figcaption{font-size:.85em;color:#555;text-align:center}\n",
            "</style>\n</head>\n<body>\n",
        ));
        for block in self.blocks() {
            match block {
                Block::Title(t) => {
                    let _ = writeln!(out, "<h1>{}</h1>", html_inline(&t));
                }
                Block::Heading(t) => {
                    let _ = writeln!(out, "<h2>{}</h2>", html_inline(&t));
                }
                Block::Para(t) => {
                    let _ = writeln!(out, "<p>{}</p>", html_inline(&t));
                }
                Block::Bullets(items) => {
                    out.push_str("<ul>\n");
                    for i in items {
                        let _ = writeln!(out, "<li>{}</li>", html_inline(&i));
                    }
                    out.push_str("</ul>\n");
                }
                Block::Table { head, rows } => {
                    let class = |h: &String| if is_text(h) { " class=\"t\"" } else { "" };
                    out.push_str("<table>\n<thead><tr>");
                    for h in &head {
                        let _ = write!(out, "<th{}>{}</th>", class(h), html_inline(h));
                    }
                    out.push_str("</tr></thead>\n<tbody>\n");
                    for r in &rows {
                        out.push_str("<tr>");
                        for (c, h) in r.iter().zip(&head) {
                            let _ = write!(out, "<td{}>{}</td>", class(h), html_inline(c));
                        }
                        out.push_str("</tr>\n");
                    }
                    out.push_str("</tbody>\n</table>\n");
                }
                Block::Plots => {
                    for p in &self.plots {
                        let svg = p.svg.find("<svg").map_or("", |i| &p.svg[i..]);
                        let _ = writeln!(
                            out,
                            "<figure id=\"{}\">\n{}\n<figcaption>{}</figcaption>\n</figure>",
                            esc(&p.name),
                            svg.trim_end(),
                            esc(&p.title)
                        );
                    }
                }
                Block::Image(alt, path) => {
                    let _ = writeln!(
                        out,
                        "<figure><img src=\"{}\" alt=\"{}\"><figcaption>{}</figcaption></figure>",
                        esc(&path),
                        esc(&alt),
                        esc(&alt)
                    );
                }
            }
        }
        out.push_str("</body>\n</html>\n");
        out
    }

    /// Writes `report.md`, `report.html`, `report.json` (the tables as data: every field of
    /// the report but the plots) and every plot as `plots/<name>.svg` and `plots/<name>.png`
    /// into `dir` (created if needed); returns the paths written, in that order.
    ///
    /// # Errors
    ///
    /// [`ReportError::Io`] naming the path, [`ReportError::Plot`] if a PNG cannot be drawn.
    pub fn write(&self, dir: &Path) -> Result<Vec<PathBuf>, ReportError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| ReportError::Io { path, source }
        };
        let plots_dir = dir.join("plots");
        std::fs::create_dir_all(&plots_dir).map_err(io(&plots_dir))?;
        let mut written = Vec::new();
        let mut put = |path: PathBuf, bytes: &[u8]| -> Result<(), ReportError> {
            std::fs::write(&path, bytes).map_err(io(&path))?;
            written.push(path);
            Ok(())
        };
        put(dir.join("report.md"), self.markdown().as_bytes())?;
        put(dir.join("report.html"), self.html().as_bytes())?;
        let json_path = dir.join("report.json");
        let json = serde_json::to_string_pretty(self)
            .map_err(|e| io(&json_path)(std::io::Error::other(e)))?;
        put(json_path, json.as_bytes())?;
        for p in &self.plots {
            put(plots_dir.join(format!("{}.svg", p.name)), p.svg.as_bytes())?;
            put(plots_dir.join(format!("{}.png", p.name)), &p.png()?)?;
        }
        Ok(written)
    }
}

/// Columns holding text (left-aligned); the others hold numbers (right-aligned).
pub(super) fn is_text(header: &str) -> bool {
    matches!(header, "cell" | "corruption" | "arm" | "regime" | "error")
}

/// Escapes a Markdown table cell (pipes, line breaks).
pub(super) fn md_cell(s: &str) -> String {
    md_inline(s).replace('|', "\\|")
}

/// Keeps Markdown text on one line.
pub(super) fn md_inline(s: &str) -> String {
    s.replace(['\r', '\n'], " ")
}

/// Escapes HTML text.
pub(super) fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            _ => out.push(c),
        }
    }
    out
}

/// Escapes HTML text and turns balanced `code` spans into `<code>`.
pub(super) fn html_inline(s: &str) -> String {
    let parts: Vec<&str> = s.split('`').collect();
    if parts.len().is_multiple_of(2) {
        return esc(s);
    }
    parts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i % 2 == 1 {
                format!("<code>{}</code>", esc(p))
            } else {
                esc(p)
            }
        })
        .collect()
}

/// A recovered fraction on coverage with its paired standard error (`1.88 ± 0.61`), `n/a`
/// where undefined.
pub(super) fn fraction_se(r: &Recovered) -> String {
    value_se(r.coverage, r.coverage_se)
}

/// A fraction with its standard error where it has one, "n/a" where it is undefined.
fn value_se(v: Option<f64>, se: Option<f64>) -> String {
    match (v, se) {
        (Some(f), Some(se)) => format!("{f:.2} ± {se:.2}"),
        (Some(f), None) => format!("{f:.2}"),
        _ => "n/a".into(),
    }
}

/// The fraction against the robust arm's own clean value, with its jackknife error.
pub(super) fn own_se(r: &Recovered) -> String {
    value_se(r.coverage_own, r.coverage_own_se)
}

/// A note when a defined fraction is computed on fewer seeds than the corrupted comparison
/// pairs (`paired`): a cell that has not run every seed of its clean cell, or the reverse.
pub(super) fn partial_seeds(r: &Recovered, paired: usize) -> Option<String> {
    (r.coverage.is_some() && r.seeds < paired).then(|| {
        format!(
            "recovered on the {} of {paired} paired seeds that also ran the clean cell",
            r.seeds
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(w: Option<f64>, m: Option<f64>) -> MainRow {
        MainRow {
            cell: "c".into(),
            policy: "p".into(),
            corruption: "blank".into(),
            q: 2,
            h: 2,
            clean: None,
            robust_clean: None,
            clean_comparison: None,
            comparison: None,
            holm_wilcoxon: w,
            holm_mcnemar: m,
            recovered: Recovered::undefined(None, None),
        }
    }

    #[test]
    fn holm_sentence_counts_only_the_rows_with_a_test() {
        let all = [row(Some(0.1), Some(0.2)), row(Some(0.3), Some(0.4))];
        assert_eq!(
            holm_rows_sentence(&all),
            "Holm over the 2 rows (each test separately)."
        );
        let some = [
            row(Some(0.1), Some(0.2)),
            row(None, None),
            row(Some(0.3), None),
            row(None, None),
            row(None, None),
        ];
        assert_eq!(
            holm_rows_sentence(&some),
            "Holm over the 2 of 5 rows that have the test (Wilcoxon) and the 1 of 5 rows that \
             have the test (McNemar)."
        );
    }
}
