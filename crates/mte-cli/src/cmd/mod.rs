//! One module per subcommand: arguments in, library call, output out.

pub mod demo;
pub mod replay;
