//! The report's figures as data: which plots a run gets (coverage and success against `q`,
//! the recovered fraction against the attack budget) and their series. `plot` draws them.

use super::*;
use crate::corruption::Schedule;
use crate::label::{phase_suffix, span_suffix};

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
    specs.extend(span_plots(cells, &mut taken)?);
    Ok(specs)
}

/// Plots (c): clean mean max coverage against the span (executable rows used), per
/// (policy, h) with clean cells at two spans or more: the clean-data confound's
/// dose-response curve. Cells at the full span (no `span`) are left out, since a cell
/// spec does not know the policy's row count.
fn span_plots(
    cells: &[CellData<'_>],
    taken: &mut HashSet<String>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let spanned: Vec<usize> = (0..cells.len())
        .filter(|&ci| cells[ci].is_clean() && cells[ci].spec.span.is_some())
        .collect();
    let groups = group_by(&spanned, |ci| {
        (cells[ci].spec.policy_key(), cells[ci].spec.h)
    });
    let mut specs = Vec::new();
    for ((policy, h), mut members) in groups.into_iter().filter(|(_, m)| m.len() >= 2) {
        members.sort_by_key(|&ci| cells[ci].spec.span);
        let mut series = Vec::new();
        for arm in arms_of(cells, &members) {
            let mut points = Vec::new();
            for &ci in &members {
                let what = format!("cell `{}`, arm `{arm}`", cells[ci].spec.id);
                if let Some(e) = Estimate::of(&coverages(cells[ci].episodes(&arm)), &what)? {
                    points.push(Point {
                        x: cells[ci].spec.span.unwrap_or_default() as f64,
                        y: e.mean,
                        err: e.se,
                    });
                }
            }
            if !points.is_empty() {
                series.push(Series { label: arm, points });
            }
        }
        let label = policy_label(&policy);
        specs.push(unit_plot(
            unique(
                taken,
                format!("span-{}", slug(&format!("{label}-clean-h{h}"))),
            ),
            format!("Clean mean max coverage against span, {label}, h = {h}"),
            (
                "span (executable rows of each chunk used)",
                "mean max coverage (± SE)",
            ),
            series,
        ));
    }
    Ok(specs)
}

/// The cells `indices` grouped by `key`, groups in order of first appearance.
fn group_by<K: PartialEq>(indices: &[usize], key: impl Fn(usize) -> K) -> Vec<(K, Vec<usize>)> {
    let mut groups: Vec<(K, Vec<usize>)> = Vec::new();
    for &ci in indices {
        let k = key(ci);
        match groups.iter_mut().find(|(g, _)| *g == k) {
            Some((_, v)) => v.push(ci),
            None => groups.push((k, vec![ci])),
        }
    }
    groups
}

/// A plot on an integer x axis with y in the unit interval (coverage, success rate); `axes`
/// are the x and y labels.
fn unit_plot(name: String, title: String, axes: (&str, &str), series: Vec<Series>) -> PlotSpec {
    PlotSpec {
        name,
        title,
        x_label: axes.0.into(),
        y_label: axes.1.into(),
        integer_x: true,
        log_x: false,
        y_include: (0.0, 1.0),
        y_refs: vec![],
        series,
    }
}

/// The x label of plots against q.
const Q_AXIS: &str = "q (corrupted queries per period)";

/// What the recovered-fraction plots read.
struct RecoveredCtx<'c, 'a> {
    cells: &'c [CellData<'a>],
    baseline: &'c str,
    main: &'c [MainRow],
    defence: Option<&'c DefenceTable>,
}

/// Plots (a): coverage and success against q, per (policy, fault, schedule kind, h, span,
/// burst phase): bursts at another phase are another curve, not more points at the same q.
fn coverage_plots(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    taken: &mut HashSet<String>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let groups = group_by(corrupted, |ci| {
        let s = cells[ci].spec;
        (
            s.policy_key(),
            s.corruption.fault.to_string(),
            kind_tag(&s.corruption.schedule),
            s.h,
            s.span,
            burst_phase(&s.corruption.schedule),
        )
    });
    let mut specs = Vec::new();
    for ((policy, fault, kind, h, span, phase), members) in &groups {
        let mut points: Vec<(usize, usize)> =
            members.iter().map(|&ci| (cells[ci].spec.q(), ci)).collect();
        if let Some(cj) = clean_of(cells, members[0]) {
            points.push((0, cj));
        }
        points.sort_by_key(|&(q, ci)| (q, ci));
        let (cov, succ) = q_series(cells, &points)?;
        let label = policy_label(policy);
        let stem = slug(&format!(
            "{label}-{fault}-{kind}{}-h{h}{}",
            phase_suffix(*phase),
            span_suffix(*span)
        ));
        let title = format!(
            "{label}: {fault} ({kind}{}), h = {h}{}",
            phase_title(*phase),
            span_title(*span)
        );
        specs.push(unit_plot(
            unique(taken, format!("coverage-{stem}")),
            format!("Mean max coverage, {title}"),
            (Q_AXIS, "mean max coverage (± SE)"),
            cov,
        ));
        specs.push(unit_plot(
            unique(taken, format!("success-{stem}")),
            format!("Success rate, {title}"),
            (Q_AXIS, "success rate (± binomial SE)"),
            succ,
        ));
    }
    Ok(specs)
}

/// Coverage and success series against q over `points` (q, cell), one of each per arm that
/// has a point.
fn q_series(
    cells: &[CellData<'_>],
    points: &[(usize, usize)],
) -> Result<(Vec<Series>, Vec<Series>), ReportError> {
    let all: Vec<usize> = points.iter().map(|p| p.1).collect();
    let (mut cov, mut succ) = (Vec::new(), Vec::new());
    for arm in arms_of(cells, &all) {
        let (mut pc, mut ps) = (Vec::new(), Vec::new());
        for &(q, ci) in points {
            if let Some((c, s)) = q_point(&cells[ci], &arm, q as f64)? {
                pc.push(c);
                ps.push(s);
            }
        }
        if !pc.is_empty() {
            cov.push(Series {
                label: arm.clone(),
                points: pc,
            });
            succ.push(Series {
                label: arm,
                points: ps,
            });
        }
    }
    Ok((cov, succ))
}

/// One cell's mean max coverage (± SE) and success rate (± binomial SE) under `arm` at `x`;
/// `None` where the arm has no episode there.
fn q_point(cell: &CellData<'_>, arm: &str, x: f64) -> Result<Option<(Point, Point)>, ReportError> {
    let eps = cell.episodes(arm);
    let what = format!("cell `{}`, arm `{arm}`", cell.spec.id);
    let Some(e) = Estimate::of(&coverages(eps), &what)? else {
        return Ok(None);
    };
    let rate = success_count(eps) as f64 / eps.len() as f64;
    let se = binomial_se(rate, eps.len() as u64).map_err(stats_err(&what))?;
    let coverage = Point {
        x,
        y: e.mean,
        err: e.se,
    };
    let success = Point {
        x,
        y: rate,
        err: Some(se),
    };
    Ok(Some((coverage, success)))
}

/// Plots (b): the recovered fraction against the attack budget (or q), per (policy, fault
/// kind, h, span, burst phase) and, for PGD, per ball ([`pgd_curves`]); only cells whose
/// denominator is significantly above zero.
fn recovered_plots(
    ctx: &RecoveredCtx<'_, '_>,
    corrupted: &[usize],
    taken: &mut HashSet<String>,
) -> Result<Vec<PlotSpec>, ReportError> {
    let cells = ctx.cells;
    let groups = group_by(corrupted, |ci| {
        let s = cells[ci].spec;
        (
            s.policy_key(),
            kind_tag(&s.corruption.fault),
            s.h,
            s.span,
            burst_phase(&s.corruption.schedule),
        )
    });
    let (mut specs, mut curves) = (Vec::new(), Vec::new());
    for ((policy, tag, h, span, phase), members) in &groups {
        for (ball, cells_of_curve) in pgd_curves(cells, members) {
            let group = PlotGroup {
                policy,
                tag,
                ball,
                h: *h,
                span: *span,
                phase: *phase,
            };
            specs.extend(recovered_plot(
                ctx,
                &group,
                &cells_of_curve,
                taken,
                &mut curves,
            ));
        }
    }
    specs.extend(figure_ones(ctx.baseline, &curves, taken));
    Ok(specs)
}

/// What one recovered-fraction plot holds fixed: its policy, fault kind, PGD ball (None for
/// other faults, or where a group has one ball), stride, span and burst phase.
struct PlotGroup<'a> {
    policy: &'a str,
    tag: &'a str,
    ball: Option<Ball>,
    h: usize,
    span: Option<usize>,
    phase: usize,
}

/// A PGD curve's fixed attack: the L-infinity radius and the sign step (observation units).
#[derive(Clone, Copy)]
struct Ball {
    eps: f64,
    step: f64,
    /// Diffusion timesteps averaged per iteration.
    samples: usize,
}

/// The `members` of one plot group split by PGD ball: iterated PGD cells by (eps, step,
/// diffusion samples), each curve with the random-point controls (0 iterations) of its radius
/// and samples. One curve without a ball where the iterated cells share one (and for every
/// other fault): PGD iterations are a budget only at a fixed radius and step.
fn pgd_curves(cells: &[CellData<'_>], members: &[usize]) -> Vec<(Option<Ball>, Vec<usize>)> {
    let pgd = |ci: usize| cells[ci].spec.corruption.fault.pgd();
    let iterated: Vec<usize> = members
        .iter()
        .copied()
        .filter(|&ci| pgd(ci).is_some_and(|c| c.iterations > 0))
        .collect();
    let balls = group_by(&iterated, |ci| {
        pgd(ci).map(|c| (c.eps.to_bits(), c.step.to_bits(), c.samples))
    });
    if balls.len() <= 1 {
        return vec![(None, members.to_vec())];
    }
    balls
        .into_iter()
        .filter_map(|(key, mut v)| {
            let (eps, step, samples) = key?;
            v.extend(members.iter().copied().filter(|&ci| {
                pgd(ci).is_some_and(|c| {
                    c.iterations == 0 && c.eps.to_bits() == eps && c.samples == samples
                })
            }));
            v.sort_unstable();
            let (eps, step) = (f64::from_bits(eps), f64::from_bits(step));
            Some((Some(Ball { eps, step, samples }), v))
        })
        .collect()
}

/// One recovered-fraction plot of `group` over the cells `members` (None where no cell has a
/// point), its budget curve pushed onto `curves` for Figure 1 where it has one.
fn recovered_plot(
    ctx: &RecoveredCtx<'_, '_>,
    group: &PlotGroup<'_>,
    members: &[usize],
    taken: &mut HashSet<String>,
    curves: &mut Vec<Curve>,
) -> Option<PlotSpec> {
    let PlotGroup {
        policy,
        tag,
        ball,
        h,
        span,
        phase,
    } = *group;
    let cells = ctx.cells;
    let (ball_title, ball_suffix) = ball.map_or_else(Default::default, |b| {
        (
            format!(" (eps {}, step {}, {} samples)", b.eps, b.step, b.samples),
            format!("-eps{}-step{}", b.eps, b.step),
        )
    });
    let kind = format!("{tag}{}{ball_title}", phase_title(phase));
    let budgeted: Vec<usize> = members
        .iter()
        .copied()
        .filter(|&ci| cells[ci].spec.budget().is_some())
        .collect();
    let by_budget = differ_in_budget(ctx, &budgeted);
    let used = if by_budget { &budgeted } else { members };
    let series = recovered_series(ctx, policy, used, by_budget);
    if series.is_empty() {
        return None;
    }
    // The budgets that have a point (a control at budget 0 has none: its denominator is
    // not significant, or it would be an attack).
    let xs: Vec<f64> = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.x))
        .collect();
    let base = xs
        .iter()
        .copied()
        .filter(|&x| x > 0.0)
        .fold(f64::INFINITY, f64::min);
    if by_budget && base.is_finite() {
        curves.push(Curve {
            policy: policy.to_string(),
            kind: format!("{kind}, h = {h}{}", span_title(span)),
            base,
            series: series.clone(),
        });
    }
    let label = policy_label(policy);
    let stem = format!(
        "{label}-{tag}{ball_suffix}{}-h{h}{}",
        phase_suffix(phase),
        span_suffix(span)
    );
    Some(PlotSpec {
        name: unique(taken, format!("recovered-{}", slug(&stem))),
        title: format!(
            "Recovered fraction vs {}, {label}: {kind}, h = {h}{}",
            ctx.baseline,
            span_title(span)
        ),
        x_label: if by_budget {
            cells[used[0]].spec.corruption.fault.budget_axis().into()
        } else {
            Q_AXIS.into()
        },
        y_label: "recovered fraction (± paired jackknife SE)".into(),
        integer_x: !by_budget,
        log_x: by_budget && spans_decades(&xs),
        y_include: (0.0, 1.0),
        y_refs: vec![0.0, 1.0],
        series,
    })
}

/// The series of one recovered-fraction plot over the cells `used`: each robust arm's (split
/// by schedule where the plot goes against the budget and the cells have several schedules),
/// then the defended policy's, where a defence table names this `policy` as the undefended one.
fn recovered_series(
    ctx: &RecoveredCtx<'_, '_>,
    policy: &str,
    used: &[usize],
    by_budget: bool,
) -> Vec<Series> {
    let schedules = distinct(used.iter().map(|&ci| schedule_label(ctx.cells[ci].spec)));
    let split = by_budget && schedules.len() > 1;
    let mut series: Vec<Series> = Vec::new();
    for arm in arms_of(ctx.cells, used)
        .iter()
        .filter(|a| *a != ctx.baseline)
    {
        if split {
            for sched in &schedules {
                series.extend(arm_series(ctx, used, by_budget, arm, Some(sched)));
            }
        } else {
            series.extend(arm_series(ctx, used, by_budget, arm, None));
        }
    }
    series.extend(defended_series(ctx, policy, used, by_budget));
    series
}

/// Whether a recovered-fraction plot over the `budgeted` cells goes against the budget: only
/// where the plotted cells differ in it (one budget at several q plots against q). A budget-0
/// cell (a random-point control) counts only where it has a recovered fraction, i.e. a point
/// to draw; otherwise it would put a lone budget on the axis.
fn differ_in_budget(ctx: &RecoveredCtx<'_, '_>, budgeted: &[usize]) -> bool {
    let plotted = |ci: usize| {
        let id = &ctx.cells[ci].spec.id;
        ctx.main
            .iter()
            .any(|r| &r.cell == id && r.recovered.coverage.is_some())
    };
    let mut budgets: Vec<f64> = budgeted
        .iter()
        .filter_map(|&ci| {
            let b = ctx.cells[ci].spec.budget()?;
            (b > 0.0 || plotted(ci)).then_some(b)
        })
        .collect();
    budgets.sort_by(f64::total_cmp);
    budgets.dedup();
    budgets.len() >= 2
}

/// The two series of one arm on a recovered-fraction plot over the cells `used` (only those
/// of schedule `only`, where the plot splits by schedule): the paper's fraction and the
/// fraction against the arm's own clean value, each sorted by x; empty series left out.
fn arm_series(
    ctx: &RecoveredCtx<'_, '_>,
    used: &[usize],
    by_budget: bool,
    arm: &str,
    only: Option<&str>,
) -> Vec<Series> {
    let (cells, baseline) = (ctx.cells, ctx.baseline);
    let (mut pts, mut own) = (Vec::new(), Vec::new());
    for &ci in used {
        let c = &cells[ci];
        if only.is_some_and(|s| schedule_label(c.spec) != s) || !c.has(arm) || !c.has(baseline) {
            continue;
        }
        let row = ctx.main.iter().find(|r| r.cell == c.spec.id);
        let x = axis_x(c.spec, by_budget);
        if let Some((p, o)) = recovered_point(cells, ci, row, baseline, arm, x) {
            pts.push(p);
            own.extend(o);
        }
    }
    let label = only.map_or_else(|| arm.to_string(), |s| format!("{arm}, {s}"));
    [(pts, label.clone()), (own, format!("{label}, own clean"))]
        .into_iter()
        .filter(|(points, _)| !points.is_empty())
        .map(|(mut points, label)| {
            points.sort_by(|a, b| a.x.total_cmp(&b.x));
            Series { label, points }
        })
        .collect()
}

/// Figure 1 for every policy with two or more budget curves, in the curves' order.
fn figure_ones(baseline: &str, curves: &[Curve], taken: &mut HashSet<String>) -> Vec<PlotSpec> {
    distinct(curves.iter().map(|c| c.policy.as_str()))
        .into_iter()
        .filter_map(|policy| {
            let own: Vec<&Curve> = curves.iter().filter(|c| c.policy == policy).collect();
            (own.len() >= 2).then(|| figure_one(baseline, policy, &own, taken))
        })
        .collect()
}

/// One budget curve of a policy's recovered-fraction plots (with the defence's series where
/// the report has one), for Figure 1.
struct Curve {
    policy: String,
    /// Fault kind and stride (`pgd, h = 2`).
    kind: String,
    /// The curve's smallest positive budget with a point: its attack's own baseline effort.
    base: f64,
    series: Vec<Series>,
}

/// The paper's Figure 1 as one plot: every budget curve of one policy with two or more
/// (the rank statistics' series and, on the undefended policy of a defence table, the
/// defence's, one curve per attack kind and stride) against optimisation effort relative
/// to each attack's own baseline (its curve's smallest budget: PGD iterations, patch step
/// size), on a logarithmic axis where the efforts span a decade.
fn figure_one(
    baseline: &str,
    policy: &str,
    curves: &[&Curve],
    taken: &mut HashSet<String>,
) -> PlotSpec {
    let series: Vec<Series> = curves
        .iter()
        .flat_map(|c| {
            c.series.iter().map(|s| Series {
                label: format!("{}, {}", s.label, c.kind),
                points: s
                    .points
                    .iter()
                    .map(|p| Point {
                        x: p.x / c.base,
                        ..*p
                    })
                    .collect(),
            })
        })
        .collect();
    let xs: Vec<f64> = series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.x))
        .collect();
    let label = policy_label(policy);
    PlotSpec {
        name: unique(taken, format!("figure-1-{}", slug(label))),
        title: format!("Recovered fraction vs {baseline} against optimisation effort, {label}"),
        x_label: "optimisation effort relative to the attack's own baseline (x)".into(),
        y_label: "recovered fraction (± paired jackknife SE)".into(),
        integer_x: false,
        log_x: spans_decades(&xs),
        y_include: (0.0, 1.0),
        y_refs: vec![0.0, 1.0],
        series,
    }
}

/// Whether positive values span at least a factor of 10 (a logarithmic axis then reads
/// better).
fn spans_decades(xs: &[f64]) -> bool {
    let (lo, hi) = xs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x), hi.max(x))
        });
    lo > 0.0 && hi.is_finite() && hi / lo >= 10.0
}

/// The recovered fraction of `arm` against `baseline` on cell `ci` at `x`, where the main
/// table's denominator is significantly above zero: the report's own rule
/// ([`super::recovered`]) on the seeds that ran the clean cell, the corrupted baseline and
/// the arm, with its paired jackknife standard error (no error bar where the jackknife is
/// undefined), so a plotted point is always the value a table prints; and beside it the
/// fraction against the arm's own clean value, where defined, so that a clean-data gap
/// between the arms shows on the figure as the distance between the two. No point without
/// a clean cell to pair with.
fn recovered_point(
    cells: &[CellData<'_>],
    ci: usize,
    row: Option<&MainRow>,
    baseline: &str,
    arm: &str,
    x: f64,
) -> Option<(Point, Option<Point>)> {
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
    let own = rec.coverage_own.filter(|y| y.is_finite()).map(|y| Point {
        x,
        y,
        err: rec.coverage_own_se,
    });
    Some((
        Point {
            x,
            y,
            err: rec.coverage_se,
        },
        own,
    ))
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

/// A burst schedule's phase (0 for any other schedule).
fn burst_phase(s: &Schedule) -> usize {
    match s {
        Schedule::Burst { phase, .. } => *phase,
        _ => 0,
    }
}

/// A plot title's phase part.
fn phase_title(phase: usize) -> String {
    if phase == 0 {
        String::new()
    } else {
        format!(", phase {phase}")
    }
}

/// A plot title's span part.
fn span_title(span: Option<usize>) -> String {
    span.map_or(String::new(), |s| format!(", span {s}"))
}
