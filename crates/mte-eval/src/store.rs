//! The results store: a run directory written append-only, one JSONL file per cell.
//!
//! Every finished episode is one line, written and flushed (and synced) before the next
//! starts, so killing the process loses at most the episode in flight. A line cut short by a
//! kill is detected on resume (it does not end in a newline), removed, and its episode run
//! again. The layout is described in [`crate::record`].

use std::collections::HashSet;
use std::fs::{self, File, OpenOptions};
use std::io::{BufRead, BufReader, Read as _, Seek as _, SeekFrom, Write as _};
use std::path::{Path, PathBuf};

use crate::record::{CellSpec, Line, Manifest, RUN_FORMAT};

/// Errors of the results store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A file did not parse.
    #[error("{path}, line {line}: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line (0 for a whole-file document).
        line: usize,
        /// What was wrong.
        reason: String,
    },
    /// The directory already holds a run and neither resume nor a matching shard was asked.
    #[error("{path} already holds a run: pass --resume to continue it, or choose another --out")]
    Exists {
        /// The run directory.
        path: PathBuf,
    },
    /// Resuming with a spec whose grid differs from the stored one.
    #[error("{path}: the stored grid differs from this spec ({detail}); use a new --out")]
    Mismatch {
        /// The manifest.
        path: PathBuf,
        /// First difference.
        detail: String,
    },
    /// Not a run directory.
    #[error("{path}: not an mte run directory (expected manifest.json with format {RUN_FORMAT})")]
    NotARun {
        /// The path given.
        path: PathBuf,
    },
    /// A cell asked for by name is not a cell of the runs.
    #[error("cell `{cell}` is not a cell of the runs (cells: {available})")]
    UnknownCell {
        /// The cell id given.
        cell: String,
        /// The runs' cell ids, comma separated.
        available: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Whether the spec keeps every stored cell, each with the same seeds or more seeds appended
/// (a run grows to a larger n: the stored episodes stay paired and valid), and at most adds
/// cells of new ids (a run grows by a row: a new `q`, a new corruption). Anything else (a
/// stored cell missing or defined differently) is a mismatch naming the first such cell.
fn check_same_grid(stored: &Manifest, spec: &Manifest, mpath: &Path) -> Result<(), StoreError> {
    let extends = |a: &CellSpec, b: &CellSpec| b.seeds.starts_with(&a.seeds) && a.same_but_seeds(b);
    for a in &stored.cells {
        let detail = match spec.cells.iter().find(|b| b.id == a.id) {
            Some(b) if extends(a, b) => continue,
            Some(_) => format!("cell {} is defined differently", a.id),
            None => format!("cell {} is not in this spec", a.id),
        };
        return Err(StoreError::Mismatch {
            path: mpath.to_path_buf(),
            detail,
        });
    }
    Ok(())
}

/// An open run directory.
#[derive(Debug, Clone)]
pub struct RunDir {
    root: PathBuf,
}

impl RunDir {
    /// Creates `root` with `spec.toml` and `manifest.json`, or opens it when it already holds
    /// the same grid (or a grid this spec grows: more seeds, more cells) and `resume` (or
    /// `shared`: several shards writing one directory) is set.
    pub fn create(
        root: &Path,
        spec_toml: &str,
        manifest: &Manifest,
        resume: bool,
    ) -> Result<Self, StoreError> {
        let mpath = root.join("manifest.json");
        if mpath.exists() {
            if !resume {
                return Err(StoreError::Exists {
                    path: root.to_path_buf(),
                });
            }
            let stored = read_manifest(root)?;
            check_same_grid(&stored, manifest, &mpath)?;
            let mut merged = stored.clone();
            merged.cells.clone_from(&manifest.cells);
            merge_machines(&mut merged, manifest);
            if merged != stored {
                write_manifest(&mpath, &merged)?;
            }
            if merged.cells != stored.cells {
                write_atomic(&root.join("spec.toml"), spec_toml.as_bytes())?;
            }
        } else {
            fs::create_dir_all(root.join("cells")).map_err(io(root))?;
            write_atomic(&root.join("spec.toml"), spec_toml.as_bytes())?;
            write_manifest(&mpath, manifest)?;
        }
        fs::create_dir_all(root.join("cells")).map_err(io(root))?;
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    /// The directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Path of a cell's file.
    pub fn cell_path(&self, cell: &str) -> PathBuf {
        self.root.join("cells").join(format!("{cell}.jsonl"))
    }

    /// The (arm, seed) pairs already finished in `cell` (episodes, not errors: a failed
    /// episode is tried again on resume). A trailing partial line is removed.
    pub fn finished(&self, cell: &str) -> Result<HashSet<(String, u64)>, StoreError> {
        let path = self.cell_path(cell);
        if !path.exists() {
            return Ok(HashSet::new());
        }
        repair_tail(&path)?;
        let mut done = HashSet::new();
        for line in read_lines(&path)? {
            if let Line::Episode(e) = line {
                done.insert((e.arm, e.seed));
            }
        }
        Ok(done)
    }

    /// Opens a cell's file for appending.
    pub fn writer(&self, cell: &str) -> Result<CellWriter, StoreError> {
        let path = self.cell_path(cell);
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io(&path))?;
        Ok(CellWriter { path, file })
    }
}

/// Appends lines to one cell's file, each flushed to disk before `append` returns.
#[derive(Debug)]
pub struct CellWriter {
    path: PathBuf,
    file: File,
}

impl CellWriter {
    /// Writes one line and syncs it.
    pub fn append(&mut self, line: &Line) -> Result<(), StoreError> {
        let mut text = serde_json::to_string(line).map_err(|e| StoreError::Parse {
            path: self.path.clone(),
            line: 0,
            reason: e.to_string(),
        })?;
        text.push('\n');
        self.file
            .write_all(text.as_bytes())
            .map_err(io(&self.path))?;
        self.file.flush().map_err(io(&self.path))?;
        self.file.sync_data().map_err(io(&self.path))
    }
}

/// Writes through a temporary file and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let tmp = path.with_extension("tmp");
    fs::write(&tmp, bytes).map_err(io(&tmp))?;
    fs::rename(&tmp, path).map_err(io(path))
}

/// Truncates a final line that lacks its newline (a write cut short by a kill).
fn repair_tail(path: &Path) -> Result<(), StoreError> {
    let mut f = OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .map_err(io(path))?;
    let mut bytes = Vec::new();
    f.read_to_end(&mut bytes).map_err(io(path))?;
    if bytes.is_empty() || bytes.ends_with(b"\n") {
        return Ok(());
    }
    let keep = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
    f.set_len(keep as u64).map_err(io(path))?;
    f.seek(SeekFrom::End(0)).map_err(io(path))?;
    Ok(())
}

/// Parses every complete line of a cell file; a final line without its newline (a write
/// in flight) is ignored, any other bad line is an error naming it.
pub fn read_lines(path: &Path) -> Result<Vec<Line>, StoreError> {
    let f = File::open(path).map_err(io(path))?;
    let mut r = BufReader::new(f);
    let mut out = Vec::new();
    let mut buf = String::new();
    let mut n = 0;
    loop {
        buf.clear();
        let got = r.read_line(&mut buf).map_err(io(path))?;
        if got == 0 {
            break;
        }
        n += 1;
        if !buf.ends_with('\n') {
            break;
        }
        if buf.trim().is_empty() {
            continue;
        }
        let line: Line = serde_json::from_str(&buf).map_err(|e| StoreError::Parse {
            path: path.to_path_buf(),
            line: n,
            reason: e.to_string(),
        })?;
        out.push(line);
    }
    Ok(out)
}

/// Writes `manifest` to `path` atomically.
fn write_manifest(path: &Path, manifest: &Manifest) -> Result<(), StoreError> {
    let text = serde_json::to_string_pretty(manifest).map_err(|e| StoreError::Parse {
        path: path.to_path_buf(),
        line: 0,
        reason: e.to_string(),
    })?;
    write_atomic(path, text.as_bytes())
}

/// Appends to `acc.machines` each machine of `other` it does not list yet.
fn merge_machines(acc: &mut Manifest, other: &Manifest) {
    for m in &other.machines {
        if !acc.machines.contains(m) {
            acc.machines.push(m.clone());
        }
    }
}

/// Reads a run's manifest.
pub fn read_manifest(root: &Path) -> Result<Manifest, StoreError> {
    let path = root.join("manifest.json");
    if !path.exists() {
        return Err(StoreError::NotARun {
            path: root.to_path_buf(),
        });
    }
    let text = fs::read_to_string(&path).map_err(io(&path))?;
    let m: Manifest = serde_json::from_str(&text).map_err(|e| StoreError::Parse {
        path: path.clone(),
        line: e.line(),
        reason: e.to_string(),
    })?;
    if m.format != RUN_FORMAT {
        return Err(StoreError::NotARun {
            path: root.to_path_buf(),
        });
    }
    Ok(m)
}

/// Reads one or more run directories (shards of one grid, or separate runs) into one
/// manifest and every line. Cells are merged by id in the order first seen; a cell id
/// defined differently in two directories is an error.
pub fn load_runs(roots: &[PathBuf]) -> Result<(Manifest, Vec<Line>), StoreError> {
    let mut merged: Option<Manifest> = None;
    let mut lines = Vec::new();
    for root in roots {
        let m = read_manifest(root)?;
        match merged.as_mut() {
            None => merged = Some(m.clone()),
            Some(acc) => {
                for c in &m.cells {
                    match acc.cells.iter().find(|x| x.id == c.id) {
                        Some(x) if !(x.seeds == c.seeds && x.same_but_seeds(c)) => {
                            return Err(StoreError::Mismatch {
                                path: root.join("manifest.json"),
                                detail: format!("cell {} defined differently", c.id),
                            });
                        }
                        Some(_) => {}
                        None => acc.cells.push(c.clone()),
                    }
                }
                merge_machines(acc, &m);
            }
        }
        for c in &m.cells {
            let path = root.join("cells").join(format!("{}.jsonl", c.id));
            if path.exists() {
                lines.extend(read_lines(&path)?);
            }
        }
    }
    let m = merged.ok_or_else(|| StoreError::NotARun {
        path: PathBuf::new(),
    })?;
    Ok((m, lines))
}

/// Keeps only the cells named in `ids` (and their lines) of a loaded set of runs, in the
/// manifest's order, so that a report's tables, and the families its multiple-test corrections
/// count, hold those cells alone. Every id must name a cell; an empty `ids` keeps everything.
///
/// # Errors
///
/// [`StoreError::UnknownCell`] for an id that is not a cell of the manifest.
pub fn keep_cells(
    manifest: &mut Manifest,
    lines: &mut Vec<Line>,
    ids: &[String],
) -> Result<(), StoreError> {
    if ids.is_empty() {
        return Ok(());
    }
    if let Some(missing) = ids
        .iter()
        .find(|id| !manifest.cells.iter().any(|c| &c.id == *id))
    {
        return Err(StoreError::UnknownCell {
            cell: missing.clone(),
            available: manifest
                .cells
                .iter()
                .map(|c| c.id.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        });
    }
    let kept = |cell: &str| ids.iter().any(|id| id == cell);
    manifest.cells.retain(|c| kept(&c.id));
    lines.retain(|l| match l {
        Line::Episode(e) => kept(&e.cell),
        Line::Error(e) => kept(&e.cell),
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::corruption::CorruptionSpec;
    use crate::record::{CellSpec, EpisodeRecord, ErrorRecord, StageTimes};

    fn manifest() -> Manifest {
        Manifest {
            format: RUN_FORMAT.into(),
            name: "t".into(),
            git_commit: None,
            mte_version: "0".into(),
            created_unix_s: 0,
            noise_seed: 0,
            cells: vec![CellSpec {
                id: "c0".into(),
                policy: "p".into(),
                corruption: CorruptionSpec::CLEAN,
                h: 2,
                arms: vec!["median".into()],
                seeds: vec![1, 2],
                max_steps: 10,
                span: None,
            }],
            machines: vec![machine("cpu A")],
        }
    }

    fn machine(model: &str) -> crate::machine::Machine {
        crate::machine::Machine {
            cpu_model: model.into(),
            vector_extensions: vec!["avx2".into()],
            logical_cpus: 2,
            target: "x86_64-linux".into(),
            accelerator: None,
        }
    }

    fn episode(seed: u64) -> Line {
        Line::Episode(EpisodeRecord {
            cell: "c0".into(),
            arm: "median".into(),
            seed,
            success: false,
            max_coverage: 0.5,
            steps: 10,
            queries: 5,
            corrupted_queries: 0,
            m_counts: vec![0, 10],
            q_counts: vec![10],
            bracket: None,
            times: StageTimes::default(),
            monitors: Default::default(),
        })
    }

    #[test]
    fn keep_cells_keeps_the_named_cells_and_their_lines_only() {
        let mut m = manifest();
        let mut other = m.cells[0].clone();
        other.id = "c1".into();
        m.cells.push(other);
        let in_c1 = |l: &Line| {
            let mut l = l.clone();
            match &mut l {
                Line::Episode(e) => e.cell = "c1".into(),
                Line::Error(e) => e.cell = "c1".into(),
            }
            l
        };
        let error = Line::Error(ErrorRecord {
            cell: "c0".into(),
            arm: None,
            seed: Some(1),
            error: "worker crashed".into(),
        });
        let all = vec![episode(1), in_c1(&episode(1)), in_c1(&error), error.clone()];

        let (mut m1, mut l1) = (m.clone(), all.clone());
        keep_cells(&mut m1, &mut l1, &["c1".into()]).expect("c1 is a cell");
        assert_eq!(m1.cells.len(), 1);
        assert_eq!(m1.cells[0].id, "c1");
        assert_eq!(l1, vec![in_c1(&episode(1)), in_c1(&error)]);

        let (mut m2, mut l2) = (m.clone(), all.clone());
        keep_cells(&mut m2, &mut l2, &[]).expect("nothing asked");
        assert_eq!((m2, l2), (m.clone(), all.clone()));

        let (mut m3, mut l3) = (m.clone(), all.clone());
        let e = keep_cells(&mut m3, &mut l3, &["c1".into(), "c9".into()]).expect_err("c9");
        assert!(
            matches!(&e, StoreError::UnknownCell { cell, available } if cell == "c9" && available == "c0, c1"),
            "{e}"
        );
        assert_eq!((m3, l3), (m, all), "a refused call changes nothing");
    }

    #[test]
    fn appends_survive_and_a_cut_line_is_repaired_on_resume() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let root = dir.path().join("run");
        let run = RunDir::create(&root, "name = 't'\n", &manifest(), false)?;
        let mut w = run.writer("c0")?;
        w.append(&episode(1))?;
        w.append(&Line::Error(ErrorRecord {
            cell: "c0".into(),
            arm: Some("median".into()),
            seed: Some(2),
            error: "boom".into(),
        }))?;
        drop(w);
        // A kill in the middle of the next write.
        let path = run.cell_path("c0");
        let mut f = OpenOptions::new()
            .append(true)
            .open(&path)
            .map_err(io(&path))?;
        f.write_all(br#"{"kind":"episode","cell":"c0","ar"#)
            .map_err(io(&path))?;
        drop(f);
        assert!(matches!(
            RunDir::create(&root, "", &manifest(), false),
            Err(StoreError::Exists { .. })
        ));
        let run = RunDir::create(&root, "", &manifest(), true)?;
        let done = run.finished("c0")?;
        assert_eq!(done, HashSet::from([("median".to_string(), 1)]));
        let mut w = run.writer("c0")?;
        w.append(&episode(2))?;
        let lines = read_lines(&path)?;
        assert_eq!(lines.len(), 3);
        assert_eq!(lines[2], episode(2));
        let (m, all) = load_runs(&[root.clone(), root.clone()])?;
        assert_eq!(m.cells.len(), 1);
        assert_eq!(all.len(), 6);
        Ok(())
    }

    #[test]
    fn a_resume_on_another_machine_is_recorded_once() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let root = dir.path().join("run");
        RunDir::create(&root, "", &manifest(), false)?;
        let elsewhere = Manifest {
            machines: vec![machine("cpu B")],
            ..manifest()
        };
        // Same machine: the manifest is untouched; another machine: appended, once.
        RunDir::create(&root, "", &manifest(), true)?;
        assert_eq!(read_manifest(&root)?.machines, vec![machine("cpu A")]);
        RunDir::create(&root, "", &elsewhere, true)?;
        RunDir::create(&root, "", &elsewhere, true)?;
        let stored = read_manifest(&root)?;
        assert_eq!(stored.machines, vec![machine("cpu A"), machine("cpu B")]);
        assert_eq!(stored.cells, manifest().cells);
        // Shards written on different machines merge their machine lists.
        let other = dir.path().join("shard");
        RunDir::create(&other, "", &elsewhere, false)?;
        let (m, _) = load_runs(&[other, root])?;
        assert_eq!(m.machines, vec![machine("cpu B"), machine("cpu A")]);
        Ok(())
    }

    #[test]
    fn resume_with_another_grid_is_refused_and_bad_lines_are_named() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let root = dir.path().join("run");
        RunDir::create(&root, "", &manifest(), false)?;
        // More seeds appended: the run grows, and its manifest and spec say so.
        let mut more = manifest();
        more.cells[0].seeds.push(3);
        RunDir::create(&root, "seeds = 3", &more, true)?;
        assert_eq!(read_manifest(&root)?.cells[0].seeds, vec![1, 2, 3]);
        let spec = fs::read_to_string(root.join("spec.toml")).map_err(io(&root))?;
        assert_eq!(spec, "seeds = 3");
        // A new cell appended: the run grows by a row; the stored cells stay as they were.
        let mut row = more.clone();
        row.cells.push(CellSpec {
            id: "c1".into(),
            h: 4,
            ..more.cells[0].clone()
        });
        RunDir::create(&root, "rows = 2", &row, true)?;
        let grown = read_manifest(&root)?;
        assert_eq!(grown.cells, row.cells);
        // The same checkpoint named from a spec in another folder: the same cells.
        let mut moved = row.clone();
        for (c, label) in moved.cells.iter_mut().zip(["x/../p", "./y/z/../../p"]) {
            c.policy = label.into();
        }
        RunDir::create(&root, "rows = 2", &moved, true)?;
        // Other seeds, fewer seeds, a stored cell changed, or a stored cell dropped: refused.
        for change in [
            |m: &mut Manifest| m.cells[0].seeds = vec![1, 5, 3],
            |m: &mut Manifest| m.cells[0].seeds = vec![1, 2],
            |m: &mut Manifest| m.cells[0].h = 4,
            |m: &mut Manifest| drop(m.cells.remove(1)),
            |m: &mut Manifest| m.cells[0].id = "c2".into(),
            |m: &mut Manifest| m.cells[0].policy = "../p".into(),
            |m: &mut Manifest| m.cells[0].policy = "q/p".into(),
        ] {
            let mut other = row.clone();
            change(&mut other);
            assert!(matches!(
                RunDir::create(&root, "", &other, true),
                Err(StoreError::Mismatch { .. })
            ));
        }
        let path = root.join("cells").join("c0.jsonl");
        fs::write(&path, "{\"kind\":\"episode\"}\n").map_err(io(&path))?;
        match read_lines(&path) {
            Err(StoreError::Parse { line, .. }) => assert_eq!(line, 1),
            other => panic!("expected a parse error, got {other:?}"),
        }
        assert!(matches!(
            read_manifest(dir.path()),
            Err(StoreError::NotARun { .. })
        ));
        Ok(())
    }
}
