//! Python bindings of mte (`import mte`): the streaming temporal ensembler, native PushT and
//! the paired statistics. The Python package (`python/mte/`) wraps these classes with the
//! conventions of LeRobot and gymnasium; errors arrive as `mte.MteError` (a `ValueError`)
//! carrying the Rust message.

use pyo3::prelude::*;

mod ensembler;
mod policy;
mod sim;
mod stats;

pyo3::create_exception!(
    _native,
    MteError,
    pyo3::exceptions::PyValueError,
    "An mte call refused its input: the message names the value and what was expected."
);

/// Converts any displayable Rust error into an [`MteError`] with its message.
pub(crate) fn err(e: impl std::fmt::Display) -> PyErr {
    MteError::new_err(e.to_string())
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("MteError", m.py().get_type::<MteError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<ensembler::PyTemporalEnsembler>()?;
    m.add_class::<policy::PyPolicy>()?;
    m.add_class::<sim::PyPushT>()?;
    m.add_class::<sim::PyVecPushT>()?;
    stats::register(m)?;
    Ok(())
}
