//! `mte.TemporalEnsembler`: one stream of chunks keyed by absolute control time.

use mte_ensemble::{Aggregator, ChunkGeometry, QueryMeta, StepReport, TemporalEnsembler};
use numpy::{PyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::err;

/// Streaming temporal ensembler (see the Python docstring in `mte/__init__.pyi`).
#[pyclass(name = "TemporalEnsembler", module = "mte._native")]
pub struct PyTemporalEnsembler {
    inner: TemporalEnsembler<Aggregator>,
}

#[pymethods]
impl PyTemporalEnsembler {
    #[new]
    #[pyo3(signature = (t_p, t_o, h, dim, aggregator = "median"))]
    fn new(t_p: usize, t_o: usize, h: usize, dim: usize, aggregator: &str) -> PyResult<Self> {
        let geometry = ChunkGeometry::new(t_p, t_o, h).map_err(err)?;
        let aggregator: Aggregator = aggregator.parse().map_err(err)?;
        let inner = TemporalEnsembler::new(geometry, dim, aggregator).map_err(err)?;
        Ok(Self { inner })
    }

    /// Inserts the chunk of the query fired at control time `t` (`t_p x dim` float32).
    #[pyo3(signature = (t, chunk, corrupted = false))]
    fn insert(
        &mut self,
        t: u64,
        chunk: PyReadonlyArrayDyn<'_, f32>,
        corrupted: bool,
    ) -> PyResult<()> {
        let meta = if corrupted {
            QueryMeta::CORRUPTED
        } else {
            QueryMeta::CLEAN
        };
        let values = chunk.as_slice().map_err(err)?;
        let g = self.inner.geometry();
        let expected = [g.t_p, self.inner.dim()];
        if chunk.shape() != expected && chunk.shape() != [g.t_p * self.inner.dim()] {
            return Err(err(format!(
                "chunk of shape {:?}: expected ({}, {}) (t_p, dim)",
                chunk.shape(),
                expected[0],
                expected[1]
            )));
        }
        self.inner.insert(t, values, meta).map_err(err)
    }

    /// The action for control time `t` (float32, `dim`) and the step report.
    fn action<'py>(
        &mut self,
        py: Python<'py>,
        t: u64,
    ) -> PyResult<(Bound<'py, PyArray1<f32>>, Bound<'py, PyDict>)> {
        let step = self.inner.action(t).map_err(err)?;
        let action = PyArray1::from_slice(py, step.action);
        Ok((action, report(py, &step.report)?))
    }

    /// Forgets every chunk and the time cursor, for a new episode.
    fn reset(&mut self) {
        self.inner.reset();
    }

    #[getter]
    fn t_p(&self) -> usize {
        self.inner.geometry().t_p
    }

    #[getter]
    fn t_o(&self) -> usize {
        self.inner.geometry().t_o
    }

    #[getter]
    fn h(&self) -> usize {
        self.inner.geometry().h
    }

    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim()
    }

    #[getter]
    fn aggregator(&self) -> String {
        self.inner.aggregator().to_string()
    }

    fn __repr__(&self) -> String {
        let g = self.inner.geometry();
        format!(
            "TemporalEnsembler(t_p={}, t_o={}, h={}, dim={}, aggregator='{}')",
            g.t_p,
            g.t_o,
            g.h,
            self.inner.dim(),
            self.inner.aggregator()
        )
    }
}

/// The step report as a dict: `tau`, `m`, `q`, `excluded`, `excluded_corrupted`, `regime`
/// (`"2q<M"`, `"2q=M"` or `"2q>M"`), `oldest_query`, `newest_query`.
fn report<'py>(py: Python<'py>, r: &StepReport) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("tau", r.tau)?;
    d.set_item("m", r.m)?;
    d.set_item("q", r.q)?;
    d.set_item("excluded", r.excluded)?;
    d.set_item("excluded_corrupted", r.excluded_corrupted)?;
    d.set_item("regime", r.regime.to_string())?;
    d.set_item("oldest_query", r.oldest_query)?;
    d.set_item("newest_query", r.newest_query)?;
    Ok(d)
}
