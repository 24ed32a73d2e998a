//! `mte synthetic`: the synthetic stress test, printed as tables.

use std::fmt::Write as _;
use std::io::Write as _;

use anyhow::{Context, Result};
use mte_ensemble::ChunkGeometry;
use mte_eval::synthetic::{self, SyntheticConfig, SyntheticReport};

use crate::args::{Cli, Format, SyntheticArgs};
use crate::progress::Bar;

/// Runs the synthetic stress test.
pub fn run(cli: &Cli, args: &SyntheticArgs) -> Result<()> {
    let cfg = SyntheticConfig {
        geometry: ChunkGeometry {
            t_p: args.t_p,
            t_o: args.t_o,
            h: args.stride,
        },
        dim: args.dim,
        steps: args.steps,
        episodes: args.episodes,
        noise_std: args.noise,
        corruption: args.corruption,
        q_values: args.q.clone(),
        aggregators: args.aggregators.clone(),
        seed: args.seed,
    };
    cfg.validate()
        .context("check the flags (--t-p, --t-o, --stride, --q, ...)")?;
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    let report = synthetic::run(&cfg, &bar)?;
    if let Some(path) = &args.out {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json).with_context(|| format!("writing {}", path.display()))?;
    }
    let text = match cli.format {
        Format::Json => serde_json::to_string_pretty(&report)? + "\n",
        Format::Text => render(&report, cli.verbose > 0),
    };
    std::io::stdout().write_all(text.as_bytes())?;
    Ok(())
}

fn fmt_p(p: Option<f64>) -> String {
    match p {
        None => "-".into(),
        Some(p) if p < 1e-3 => format!("{p:.1e}"),
        Some(p) => format!("{p:.3}"),
    }
}

/// The report as markdown-style tables: the settings, tracking error per q and aggregator,
/// the paired comparisons, the bracket table at the largest q (the baseline and the first
/// alternative; every aggregator when `verbose`) and the distribution of `M`.
pub fn render(r: &SyntheticReport, verbose: bool) -> String {
    let mut s = String::new();
    header(&mut s, &r.config);
    rmse_table(&mut s, r);
    comparisons(&mut s, r);
    bracket_table(&mut s, r, verbose);
    m_distribution(&mut s, r);
    s
}

fn header(s: &mut String, c: &SyntheticConfig) {
    let g = c.geometry;
    let _ = writeln!(
        s,
        "mte synthetic: synthetic stress test (no simulator)\n\
         T_p={} T_o={} h={} (M = {}..{}), d={}, {} episodes x {} steps per q, clean noise {} \
         (std), corrupted chunks displaced by {}, seed {}\n",
        g.t_p,
        g.t_o,
        g.h,
        g.m_min(),
        g.m_max(),
        c.dim,
        c.episodes,
        c.steps,
        c.noise_std,
        c.corruption,
        c.seed
    );
}

fn rmse_table(s: &mut String, r: &SyntheticReport) {
    let c = &r.config;
    let _ = writeln!(
        s,
        "Tracking error, RMSE over all steps (action units; lower is better)\n"
    );
    let _ = write!(s, "| q |");
    for a in &c.aggregators {
        let _ = write!(s, " {a} |");
    }
    let _ = write!(s, "\n|---|");
    for _ in &c.aggregators {
        let _ = write!(s, "---|");
    }
    s.push('\n');
    for &q in &c.q_values {
        let _ = write!(s, "| {q} |");
        for a in &c.aggregators {
            if let Some(cell) = r.cells.iter().find(|x| x.q == q && x.aggregator == *a) {
                let _ = write!(s, " {:.2} |", cell.rmse);
            }
        }
        s.push('\n');
    }
}

fn comparisons(s: &mut String, r: &SyntheticReport) {
    let _ = writeln!(
        s,
        "\nPaired over episodes against {}: mean RMSE difference (negative = better), \
         Wilcoxon signed-rank p, Holm-adjusted p\n",
        r.config.aggregators[0]
    );
    let _ = writeln!(
        s,
        "| q | aggregator | mean diff | se | p | p (Holm) |\n|---|---|---|---|---|---|"
    );
    for cmp in &r.comparisons {
        let _ = writeln!(
            s,
            "| {} | {} | {:+.2} | {} | {} | {} |",
            cmp.q,
            cmp.aggregator,
            cmp.mean_diff,
            cmp.se.map_or("-".into(), |v| format!("{v:.2}")),
            fmt_p(cmp.wilcoxon_p),
            fmt_p(cmp.holm_p)
        );
    }
}

fn bracket_table(s: &mut String, r: &SyntheticReport, verbose: bool) {
    let _ = writeln!(
        s,
        "\nBracket table: steps with at least one corrupted candidate, by regime; \"outside\" = \
         output left the range of the clean candidates, excess in bracket widths\n"
    );
    let _ = writeln!(
        s,
        "| aggregator | regime | steps | outside % | median excess | max excess |\n\
         |---|---|---|---|---|---|"
    );
    // The baseline and the first alternative; -v for all.
    let shown = if verbose { usize::MAX } else { 2 };
    for a in r.config.aggregators.iter().take(shown) {
        for cell in r
            .cells
            .iter()
            .filter(|x| x.aggregator == *a && x.q == max_q(r))
        {
            for row in &cell.bracket {
                let _ = writeln!(
                    s,
                    "| {a} (q={}) | {} | {} | {:.1} | {:.2} | {:.2} |",
                    cell.q,
                    row.regime,
                    row.steps,
                    row.outside_pct,
                    row.median_excess,
                    row.max_excess
                );
            }
        }
    }
}

fn m_distribution(s: &mut String, r: &SyntheticReport) {
    let total: u64 = r.m_histogram.iter().map(|(_, n)| n).sum();
    let _ = write!(s, "\nDistribution of M(tau):");
    for (m, n) in &r.m_histogram {
        let _ = write!(s, " M={m}: {:.1}%", 100.0 * *n as f64 / total as f64);
    }
    s.push('\n');
}

fn max_q(r: &SyntheticReport) -> usize {
    r.config.q_values.iter().copied().max().unwrap_or(0)
}
