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
    // Everything is parsed and aggregated before a byte is written.
    let stream = replay::read_stream(input).with_context(|| format!("in {name}"))?;
    let steps =
        replay::replay(&stream, args.t_o, args.aggregator).with_context(|| format!("in {name}"))?;
    let uncovered = steps.iter().filter(|s| s.action.is_none()).count();
    match &args.out {
        None => {
            let stdout = std::io::stdout();
            let mut w = BufWriter::new(stdout.lock());
            write_steps(&mut w, &steps)?;
            w.flush()?;
        }
        Some(path) => {
            let dir = path
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(".".as_ref());
            let mut tmp = tempfile::NamedTempFile::new_in(dir)
                .with_context(|| format!("creating a temporary file in {}", dir.display()))?;
            {
                let mut w = BufWriter::new(tmp.as_file_mut());
                write_steps(&mut w, &steps)?;
                w.flush()?;
            }
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
                steps.len(),
                uncovered
            );
        }
    }
    Ok(())
}

fn write_steps(w: &mut impl Write, steps: &[replay::ReplayStep]) -> Result<()> {
    for s in steps {
        serde_json::to_writer(&mut *w, s)?;
        w.write_all(b"\n")?;
    }
    Ok(())
}
