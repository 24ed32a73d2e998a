//! `mte ensemble replay`: aggregate a recorded chunk stream.

use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};

use anyhow::{Context, Result};
use mte_eval::replay;

use crate::args::{Cli, ReplayArgs};

/// Runs the replay.
pub fn run(cli: &Cli, args: &ReplayArgs) -> Result<()> {
    let name = args.file.display().to_string();
    let input: Box<dyn BufRead> = if name == "-" {
        Box::new(BufReader::new(std::io::stdin()))
    } else {
        let f = File::open(&args.file).with_context(|| format!("opening chunk stream {name}"))?;
        Box::new(BufReader::new(f))
    };
    // The whole stream is parsed and checked before a byte is written; steps are then
    // written as they are computed (memory bounded by the chunk window), to a temporary
    // file that replaces `--out` only when the replay succeeded.
    let stream = replay::read_stream(input).with_context(|| format!("in {name}"))?;
    let mut tally = Tally::default();
    let mut write = |w: &mut dyn Write| -> Result<()> {
        replay::replay_each(&stream, args.t_o, args.aggregator, |s| {
            tally.add(&s);
            serde_json::to_writer(&mut *w, &s)?;
            w.write_all(b"\n")
        })
        .with_context(|| format!("in {name}"))?;
        Ok(w.flush()?)
    };
    match &args.out {
        None => {
            let stdout = std::io::stdout();
            write(&mut BufWriter::new(stdout.lock()))?;
        }
        Some(path) => {
            let dir = path
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(".".as_ref());
            let mut tmp = tempfile::NamedTempFile::new_in(dir)
                .with_context(|| format!("creating a temporary file in {}", dir.display()))?;
            write(&mut BufWriter::new(tmp.as_file_mut()))?;
            tmp.persist(path)
                .with_context(|| format!("writing {}", path.display()))?;
        }
    }
    if !cli.quiet {
        #[allow(clippy::print_stderr)]
        {
            eprintln!(
                "replayed {} queries (t_p = {}, d = {}) with {}: {} control steps, {} without \
                 any covering chunk",
                stream.records.len(),
                stream.t_p,
                stream.dim,
                args.aggregator,
                tally.steps,
                tally.uncovered
            );
        }
    }
    Ok(())
}

/// Control steps written and those without an action (an uncovered run counts its length).
#[derive(Default)]
struct Tally {
    steps: u64,
    uncovered: u64,
}

impl Tally {
    fn add(&mut self, s: &replay::ReplayStep) {
        let n = s.through.map_or(1, |end| end - s.tau + 1);
        self.steps += n;
        if s.action.is_none() {
            self.uncovered += n;
        }
    }
}
