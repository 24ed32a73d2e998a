//! The report's figures as data: which plots a run gets (coverage and success against `q`,
//! the recovered fraction against the attack budget) and their series. `plot` draws them.

use super::*;

/// Specs of every plot: coverage and success against `q`, recovered fraction against the
/// attack budget (or `q`); with a defence table, the undefended policy's recovered-fraction
/// plots also carry the defence's own series (the paper's Figure 1: the median and encoder
/// fine-tuning on one budget axis).
pub(super) fn plots(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    baseline: &str,
    main: &[MainRow],
    defence: Option<&DefenceTable>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let mut taken = HashSet::new();
    let mut specs = coverage_plots(cells, corrupted, &mut taken)?;
    let ctx = RecoveredCtx {
        cells,
        baseline,
        main,
        defence,
    };
    specs.extend(recovered_plots(&ctx, corrupted, &mut taken)?);
    Ok(specs)
}

/// What the recovered-fraction plots read.
struct RecoveredCtx<'c, 'a> {
    cells: &'c [CellData<'a>],
    baseline: &'c str,
    main: &'c [MainRow],
    defence: Option<&'c DefenceTable>,
}

/// Plots (a): coverage and success against q, per (policy, fault, schedule kind, h).
fn coverage_plots(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    taken: &mut HashSet<String>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let mut specs = Vec::new();
    // (a) Coverage and success against q, per (policy, fault, schedule kind, h).
    // Key: (policy, fault, schedule kind, h); value: member cells.
    type QGroup = ((String, String, String, usize), Vec<usize>);
    let mut groups: Vec<QGroup> = Vec::new();
    for &ci in corrupted {
        let s = cells[ci].spec;
        let key = (
            s.policy.clone(),
            s.corruption.fault.to_string(),
            kind_tag(&s.corruption.schedule),
            s.h,
        );
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, v)) => v.push(ci),
            None => groups.push((key, vec![ci])),
        }
    }
    for ((policy, fault, kind, h), members) in &groups {
        let mut points: Vec<(usize, usize)> =
            members.iter().map(|&ci| (cells[ci].spec.q(), ci)).collect();
        if let Some(cj) = clean_of(cells, members[0]) {
            points.push((0, cj));
        }
        points.sort_by_key(|&(q, ci)| (q, ci));
        let all: Vec<usize> = points.iter().map(|p| p.1).collect();
        let arms = arms_of(cells, &all);
        let (mut cov, mut succ) = (Vec::new(), Vec::new());
        for arm in &arms {
            let (mut pc, mut ps) = (Vec::new(), Vec::new());
            for &(q, ci) in &points {
                let eps = cells[ci].episodes(arm);
                let what = format!("cell `{}`, arm `{arm}`", cells[ci].spec.id);
                if let Some(e) = Estimate::of(&coverages(eps), &what)? {
                    pc.push(Point {
                        x: q as f64,
                        y: e.mean,
                        err: e.se,
                    });
                    let rate = success_count(eps) as f64 / eps.len() as f64;
                    let se = binomial_se(rate, eps.len() as u64).map_err(stats_err(&what))?;
                    ps.push(Point {
                        x: q as f64,
                        y: rate,
                        err: Some(se),
                    });
                }
            }
            if !pc.is_empty() {
                cov.push(Series {
                    label: arm.clone(),
                    points: pc,
                });
                succ.push(Series {
                    label: arm.clone(),
                    points: ps,
                });
            }
        }
        let label = policy_label(policy);
        let stem = slug(&format!("{label}-{fault}-{kind}-h{h}"));
        let title = format!("{label}: {fault} ({kind}), h = {h}");
        let (cov_title, succ_title) = (
            format!("Mean max coverage, {title}"),
            format!("Success rate, {title}"),
        );
        let x_label = "q (corrupted queries per period)".to_string();
        specs.push(PlotSpec {
            name: unique(taken, format!("coverage-{stem}")),
            title: cov_title,
            x_label: x_label.clone(),
            y_label: "mean max coverage (± SE)".into(),
            integer_x: true,
            y_include: (0.0, 1.0),
            y_refs: vec![],
            series: cov,
        });
        specs.push(PlotSpec {
            name: unique(taken, format!("success-{stem}")),
            title: succ_title,
            x_label,
            y_label: "success rate (± binomial SE)".into(),
            integer_x: true,
            y_include: (0.0, 1.0),
            y_refs: vec![],
            series: succ,
        });
    }

    Ok(specs)
}

/// Plots (b): the recovered fraction against the attack budget (or q), per (policy, fault
/// kind, h); only cells whose denominator is significantly above zero.
fn recovered_plots(
    ctx: &RecoveredCtx<'_, '_>,
    corrupted: &[usize],
    taken: &mut HashSet<String>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let (cells, baseline, main) = (ctx.cells, ctx.baseline, ctx.main);
    let mut specs = Vec::new();
    // (b) Recovered fraction against the attack budget (or q), per (policy, fault kind, h).
    let mut groups: Vec<((String, String, usize), Vec<usize>)> = Vec::new();
    for &ci in corrupted {
        let s = cells[ci].spec;
        let key = (s.policy.clone(), kind_tag(&s.corruption.fault), s.h);
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, v)) => v.push(ci),
            None => groups.push((key, vec![ci])),
        }
    }
    let row_of = |ci: usize| main.iter().find(|r| r.cell == cells[ci].spec.id);
    for ((policy, kind, h), members) in &groups {
        let budgeted: Vec<usize> = members
            .iter()
            .copied()
            .filter(|&ci| cells[ci].spec.budget().is_some())
            .collect();
        let by_budget = budgeted.len() >= 2;
        let used = if by_budget { &budgeted } else { members };
        let schedules: Vec<String> = {
            let mut v: Vec<String> = Vec::new();
            for &ci in used {
                let s = schedule_label(cells[ci].spec);
                if !v.contains(&s) {
                    v.push(s);
                }
            }
            v
        };
        let split = by_budget && schedules.len() > 1;
        let mut series: Vec<Series> = Vec::new();
        for arm in arms_of(cells, used).iter().filter(|a| *a != baseline) {
            for sched in if split {
                schedules.clone()
            } else {
                vec![String::new()]
            } {
                let mut pts = Vec::new();
                for &ci in used {
                    let c = &cells[ci];
                    if (split && schedule_label(c.spec) != sched) || !c.has(arm) || !c.has(baseline)
                    {
                        continue;
                    }
                    let x = axis_x(c.spec, by_budget);
                    if let Some(p) = recovered_point(cells, ci, row_of(ci), baseline, arm, x) {
                        pts.push(p);
                    }
                }
                pts.sort_by(|a, b| a.x.total_cmp(&b.x));
                if !pts.is_empty() {
                    series.push(Series {
                        label: if split {
                            format!("{arm}, {sched}")
                        } else {
                            arm.clone()
                        },
                        points: pts,
                    });
                }
            }
        }
        series.extend(defended_series(ctx, policy, used, by_budget));
        if series.is_empty() {
            continue;
        }
        let label = policy_label(policy);
        specs.push(PlotSpec {
            name: unique(
                taken,
                format!("recovered-{}", slug(&format!("{label}-{kind}-h{h}"))),
            ),
            title: format!("Recovered fraction vs {baseline}, {label}: {kind}, h = {h}"),
            x_label: if by_budget {
                "attack budget".into()
            } else {
                "q (corrupted queries per period)".into()
            },
            y_label: "recovered fraction (± paired jackknife SE)".into(),
            integer_x: !by_budget,
            y_include: (0.0, 1.0),
            y_refs: vec![0.0, 1.0],
            series,
        });
    }
    Ok(specs)
}

/// The recovered fraction of `arm` against `baseline` on cell `ci` at `x`, where the main
/// table's denominator is significantly above zero: the report's own rule
/// ([`super::recovered`]) on the seeds that ran the clean cell, the corrupted baseline and
/// the arm, with its paired jackknife standard error (no error bar where the jackknife is
/// undefined), so a plotted point is always the value a table prints. No point without a
/// clean cell to pair with.
fn recovered_point(
    cells: &[CellData<'_>],
    ci: usize,
    row: Option<&MainRow>,
    baseline: &str,
    arm: &str,
    x: f64,
) -> Option<Point> {
    let (row, cj) = (row?, clean_of(cells, ci)?);
    let (c, clean) = (&cells[ci], &cells[cj]);
    let rec = super::recovered(
        super::RecoveryEpisodes {
            clean: clean.episodes(baseline),
            base: c.episodes(baseline),
            other: c.episodes(arm),
            other_clean: clean.episodes(arm),
        },
        row.recovered.denominator,
    );
    let y = rec.coverage.filter(|y| y.is_finite())?;
    Some(Point {
        x,
        y,
        err: rec.coverage_se,
    })
}

/// A cell's position on a recovered-fraction plot: its attack budget, or its `q` when the
/// plot is against `q`.
fn axis_x(spec: &CellSpec, by_budget: bool) -> f64 {
    if by_budget {
        spec.budget().unwrap_or(0.0)
    } else {
        spec.q() as f64
    }
}

/// The defence's series on the undefended `policy`'s plot over the cells `used`: at each
/// cell where the defence table has a row for the baseline arm with a defined recovered
/// fraction (`(defended − undefended) / (clean − undefended)`, both policies deployed with the
/// baseline aggregator), the table's fraction: on the seeds all three cells ran, with its
/// paired jackknife standard error.
fn defended_series(
    ctx: &RecoveredCtx<'_, '_>,
    policy: &str,
    used: &[usize],
    by_budget: bool,
) -> Option<Series> {
    let d = ctx.defence?;
    if policy != d.undefended && policy_label(policy) != d.undefended {
        return None;
    }
    let mut points = Vec::new();
    for &ci in used {
        let u = &ctx.cells[ci];
        let row = d
            .rows
            .iter()
            .find(|r| r.undefended_cell == u.spec.id && r.arm == ctx.baseline);
        let Some(rec) = row.map(|r| &r.recovered) else {
            continue;
        };
        if let Some(y) = rec.coverage.filter(|y| y.is_finite()) {
            points.push(Point {
                x: axis_x(u.spec, by_budget),
                y,
                err: rec.coverage_se,
            });
        }
    }
    points.sort_by(|a, b| a.x.total_cmp(&b.x));
    (!points.is_empty()).then(|| Series {
        label: format!("{} ({})", policy_label(&d.defended), ctx.baseline),
        points,
    })
}

/// The schedule part of a corruption's text form (`burst-q2`).
fn schedule_label(s: &CellSpec) -> String {
    let full = s.corruption.to_string();
    let fault = format!("{}-", s.corruption.fault);
    full.strip_prefix(&fault).unwrap_or(&full).to_string()
}
