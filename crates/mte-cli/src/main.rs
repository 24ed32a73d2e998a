//! The `mte` binary: argument parsing, terminal output and exit codes. Every experiment
//! lives in the libraries; this crate only turns arguments into library calls.
//!
//! Exit codes: 0 success, 2 error (the message names the value or flag to fix).

mod args;
mod cmd;
mod progress;

use std::process::ExitCode;

use clap::Parser;

use crate::args::{
    AttackCommand, Cli, Command, DataCommand, DefendCommand, EnsembleCommand, EnvCommand,
    EvalCommand, MonitorCommand, SimCommand, TrainCommand,
};

fn main() -> ExitCode {
    // Freed tensor buffers stay in the heap (no page faults per operation); see the
    // module's docs. `false` on other allocators, which are left as they are.
    mte_policy::memory::keep_freed_memory();
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Demo(a) => cmd::demo::run(&cli, a),
        Command::Film(a) => cmd::film::run(&cli, a),
        Command::Sweep(a) => cmd::sweep::run(&cli, a),
        Command::Report(a) => cmd::report::run(&cli, a),
        Command::Synthetic(a) => cmd::synthetic::run(&cli, a),
        Command::Attack(AttackCommand::Calibrate(a)) => cmd::attack::calibrate(&cli, a),
        Command::Attack(AttackCommand::Patch(a)) => cmd::attack::patch(&cli, a),
        Command::Attack(AttackCommand::Control(a)) => cmd::attack::control(&cli, a),
        Command::Attack(AttackCommand::Alignment(a)) => cmd::attack::alignment(&cli, a),
        Command::Attack(AttackCommand::Activity(a)) => cmd::attack::activity(&cli, a),
        Command::Defend(DefendCommand::Finetune(a)) => cmd::attack::finetune(&cli, a),
        Command::Defend(DefendCommand::Probe(a)) => cmd::attack::probe(&cli, a),
        Command::Monitor(MonitorCommand::Calibrate(a)) => cmd::monitor::calibrate(&cli, a),
        Command::Monitor(MonitorCommand::Evaluate(a)) => cmd::monitor::evaluate(&cli, a),
        Command::Ensemble(EnsembleCommand::Replay(a)) => cmd::replay::run(&cli, a),
        Command::Sim(SimCommand::Render(a)) => cmd::sim::render(&cli, a),
        Command::Sim(SimCommand::Rollout(a)) => cmd::sim::rollout(&cli, a),
        Command::Sim(SimCommand::Bench(a)) => cmd::sim::bench(&cli, a),
        Command::Data(DataCommand::Generate(a)) => cmd::data::generate(&cli, a),
        Command::Data(DataCommand::Takeover(a)) => cmd::data::takeover(&cli, a),
        Command::Train(TrainCommand::Diffusion(a)) => cmd::train::diffusion(&cli, a),
        Command::Train(TrainCommand::Encoder(a)) => cmd::train::encoder(&cli, a),
        Command::Train(TrainCommand::Act(a)) => cmd::train::act(&cli, a),
        Command::Eval(EvalCommand::Policy(a)) => cmd::eval::policy(&cli, a),
        Command::Env(EnvCommand::Expert(a)) => cmd::env::expert(&cli, a),
        Command::Env(EnvCommand::Bench(a)) => cmd::env::bench(&cli, a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            #[allow(clippy::print_stderr)]
            {
                eprintln!("error: {e}");
                for cause in e.chain().skip(1) {
                    eprintln!("  caused by: {cause}");
                }
            }
            ExitCode::from(2)
        }
    }
}
