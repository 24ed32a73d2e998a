//! ROC plots of the runtime monitors: one plot per (monitor, arm), one curve per corrupted
//! cell against its clean reference, beside the chance diagonal.

use super::{Plot, PlotSpec, Point, ReportError, Series, distinct};
use crate::label::slug;
use crate::monitoring::MonitorRow;

/// ROC plots of `rows` (from [`crate::monitoring::evaluate`]): rows without a curve (clean
/// cells, cells without a clean reference) are left out, and so is a (monitor, arm) with no
/// curve at all. File stems `roc-<monitor>-<arm>`.
pub fn roc_plots(rows: &[MonitorRow]) -> Result<Vec<Plot>, ReportError> {
    let keys = distinct(
        rows.iter()
            .filter(|r| !r.roc.is_empty())
            .map(|r| (r.monitor.as_str(), r.arm.as_str())),
    );
    keys.into_iter()
        .map(|(monitor, arm)| {
            let mut series: Vec<Series> = rows
                .iter()
                .filter(|r| r.monitor == monitor && r.arm == arm && !r.roc.is_empty())
                .map(|r| Series {
                    label: match r.auroc {
                        Some(a) => format!("{} (AUROC {a:.3})", r.cell),
                        None => r.cell.clone(),
                    },
                    points: points(&r.roc),
                })
                .collect();
            series.push(Series {
                label: "chance".into(),
                points: points(&[(0.0, 0.0), (1.0, 1.0)]),
            });
            Plot::new(PlotSpec {
                name: slug(&format!("roc-{monitor}-{arm}")),
                title: format!(
                    "{monitor} on {arm}: episode score (max over queries) against clean"
                ),
                x_label: "false positive rate (clean episodes)".into(),
                y_label: "true positive rate (corrupted episodes)".into(),
                integer_x: false,
                log_x: false,
                y_include: (0.0, 1.0),
                y_refs: Vec::new(),
                series,
            })
        })
        .collect()
}

fn points(roc: &[(f64, f64)]) -> Vec<Point> {
    roc.iter()
        .map(|&(x, y)| Point { x, y, err: None })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(cell: &str, monitor: &str, arm: &str, roc: Vec<(f64, f64)>) -> MonitorRow {
        MonitorRow {
            cell: cell.into(),
            arm: arm.into(),
            monitor: monitor.into(),
            episodes: 2,
            fired: 0,
            first_alarm_mean: None,
            reference: None,
            auroc: (!roc.is_empty()).then_some(0.75),
            auroc_ci: None,
            roc,
        }
    }

    #[test]
    fn one_plot_per_monitor_and_arm_with_a_curve_per_corrupted_cell() -> Result<(), ReportError> {
        let curve = vec![(0.0, 0.0), (0.0, 0.5), (1.0, 1.0)];
        let rows = [
            row("clean", "tide", "median", Vec::new()),
            row("blank", "tide", "median", curve.clone()),
            row("pgd", "tide", "median", curve.clone()),
            row("blank", "acc", "median", curve),
            row("clean", "acc", "ewm:0.01", Vec::new()),
        ];
        let plots = roc_plots(&rows)?;
        let names: Vec<&str> = plots.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["roc-tide-median", "roc-acc-median"]);
        let tide = &plots[0];
        assert_eq!(tide.spec.series.len(), 3, "two cells and the diagonal");
        assert!(
            tide.svg.contains("blank (AUROC 0.750)"),
            "the legend names the cell"
        );
        assert_eq!(tide.spec.series[0].points.len(), 3);
        Ok(())
    }
}
