//! Native PushT for mte (see the crate README section in `ARCHITECTURE.md`).
#![forbid(unsafe_code)]

pub mod geometry;
pub mod rng;
