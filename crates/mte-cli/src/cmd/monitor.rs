//! `mte monitor calibrate`, `mte monitor evaluate`.

use std::collections::BTreeMap;
use std::io::Write as _;

use anyhow::{Context, Result, bail};
use mte_ensemble::MonitorKind;
use mte_ensemble::monitor::CalibrationRule;
use mte_eval::monitoring::{Thresholds, calibrate_records, evaluate as evaluate_rows};
use mte_eval::record::{EpisodeRecord, Line};
use mte_eval::store::load_runs;

use crate::args::{Cli, Format, MonitorCalibrateArgs, MonitorEvaluateArgs};

/// A run's cells and its episode records by cell id.
type RunRecords = (
    Vec<mte_eval::record::CellSpec>,
    BTreeMap<String, Vec<EpisodeRecord>>,
);

/// Every episode record of a run (read as `mte report` reads it), by cell id.
fn records_by_cell(run: &std::path::Path) -> Result<RunRecords> {
    let (manifest, lines) =
        load_runs(&[run.to_path_buf()]).with_context(|| format!("reading {}", run.display()))?;
    let mut out: BTreeMap<String, Vec<EpisodeRecord>> = manifest
        .cells
        .iter()
        .map(|c| (c.id.clone(), Vec::new()))
        .collect();
    for line in lines {
        if let Line::Episode(e) = line {
            out.entry(e.cell.clone()).or_default().push(e);
        }
    }
    Ok((manifest.cells, out))
}

/// `mte monitor calibrate`
pub fn calibrate(cli: &Cli, a: &MonitorCalibrateArgs) -> Result<()> {
    let (cells, records) = records_by_cell(&a.run)?;
    let cell = match &a.cell {
        Some(id) => cells
            .iter()
            .find(|c| &c.id == id)
            .with_context(|| format!("--cell {id}: not a cell of {}", a.run.display()))?,
        None => {
            let clean: Vec<_> = cells.iter().filter(|c| c.corruption.is_clean()).collect();
            match clean.as_slice() {
                [one] => *one,
                [] => bail!("{} has no clean cell to calibrate on", a.run.display()),
                _ => bail!(
                    "{} has {} clean cells: choose one with --cell ({})",
                    a.run.display(),
                    clean.len(),
                    clean
                        .iter()
                        .map(|c| c.id.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            }
        }
    };
    if !cell.corruption.is_clean() {
        bail!("--cell {}: a calibration cell must be clean", cell.id);
    }
    let recs = &records[&cell.id];
    let mut monitors = BTreeMap::new();
    for kind in [MonitorKind::Tide, MonitorKind::Acc] {
        if !recs.iter().any(|r| r.monitors.contains_key(kind.name())) {
            continue;
        }
        let rule = match kind {
            MonitorKind::Tide if a.tide_episode_max => {
                CalibrationRule::EpisodeMaxConformal { alpha: a.alpha }
            }
            MonitorKind::Tide => CalibrationRule::PooledConformal { alpha: a.alpha },
            MonitorKind::Acc => CalibrationRule::EpisodeMaxCapped { delta: a.delta },
        };
        let t = calibrate_records(recs, kind, rule, &a.arm, !a.all_episodes)?;
        monitors.insert(kind.to_string(), t);
    }
    if monitors.is_empty() {
        bail!(
            "no episode of {} carries monitor scores: run it with monitors = [\"tide\", \"acc\"]",
            cell.id
        );
    }
    let thresholds = Thresholds {
        source: format!("{} / {}", a.run.display(), cell.id),
        arm: a.arm.clone(),
        successful_only: !a.all_episodes,
        monitors,
    };
    std::fs::write(&a.out, serde_json::to_string_pretty(&thresholds)? + "\n")
        .with_context(|| format!("writing {}", a.out.display()))?;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::to_string(&thresholds)?)?,
        Format::Text if !cli.quiet => {
            for (name, t) in &thresholds.monitors {
                let value = t
                    .value
                    .map_or_else(|| "none: can never fire".into(), |v| format!("{v:.6}"));
                writeln!(
                    so,
                    "{name}: {:?}, n = {} scores from {} episodes, rank k = {}, threshold {value}",
                    t.rule, t.n, t.episodes, t.k
                )?;
            }
            writeln!(so, "-> {}", a.out.display())?;
        }
        Format::Text => {}
    }
    Ok(())
}

/// `mte monitor evaluate`
pub fn evaluate(cli: &Cli, a: &MonitorEvaluateArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.thresholds)
        .with_context(|| format!("reading {}", a.thresholds.display()))?;
    let thresholds: Thresholds = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a thresholds file", a.thresholds.display()))?;
    let (cells, records) = records_by_cell(&a.run)?;
    let rows = evaluate_rows(&cells, &records, &thresholds);
    if let Some(dir) = &a.plots {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for plot in mte_eval::report::roc_plots(&rows)? {
            let path = dir.join(format!("{}.svg", plot.name));
            std::fs::write(&path, &plot.svg)
                .with_context(|| format!("writing {}", path.display()))?;
        }
    }
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({ "thresholds": thresholds, "rows": rows })
        )?,
        Format::Text => {
            writeln!(
                so,
                "{:<44} {:<10} {:<5} {:>4} {:>7} {:>8} {:>7} {:>15}",
                "cell", "arm", "mon", "n", "fired", "1st q", "AUROC", "95% CI"
            )?;
            for r in &rows {
                writeln!(
                    so,
                    "{:<44} {:<10} {:<5} {:>4} {:>6.0}% {:>8} {:>7} {:>15}",
                    r.cell,
                    r.arm,
                    r.monitor,
                    r.episodes,
                    100.0 * r.firing_rate(),
                    r.first_alarm_mean.map_or("-".into(), |v| format!("{v:.1}")),
                    r.auroc.map_or("-".into(), |v| format!("{v:.3}")),
                    r.auroc_ci
                        .map_or("-".into(), |(l, h)| format!("[{l:.3}, {h:.3}]")),
                )?;
            }
        }
    }
    Ok(())
}
