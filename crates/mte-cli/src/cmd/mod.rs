//! One module per subcommand: arguments in, library call, output out.

pub mod attack;
pub mod data;
pub mod demo;
pub mod env;
pub mod eval;
pub mod film;
pub mod media;
pub mod monitor;
pub mod replay;
pub mod report;
pub mod sim;
pub mod sweep;
pub mod synthetic;
pub mod train;
