//! One process at a time in a run folder: `fit`, `render` and `relight` hold `RUN/.lock`
//! (created exclusively, holding the process id) while they work and remove it when done, so
//! two fits cannot interleave checkpoints and a render cannot read a half-written run. A lock
//! whose process is gone (a killed fit) is taken over.

use crate::fit_error::{io, FitError};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const LOCK_FILE: &str = ".lock";

/// Held while a command works in a run folder; dropping it releases the folder.
#[derive(Debug)]
pub struct RunLock {
    path: PathBuf,
}

impl RunLock {
    /// Locks the existing folder `run` for `command`, or says which process holds it.
    pub fn acquire(run: &Path, command: &str) -> Result<Self, FitError> {
        let path = run.join(LOCK_FILE);
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut file) => {
                    writeln!(file, "{} {command}", std::process::id()).map_err(|e| io(&path, e))?;
                    return Ok(Self { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    match holder(run) {
                        Some((pid, what)) if !process_is_gone(pid) => {
                            return Err(io(
                                run,
                                format!(
                                    "another umbra {what} (process {pid}) is working in this run folder; wait for it, or remove {} if no umbra runs there",
                                    path.display()
                                ),
                            ));
                        }
                        // A lock left by a process that no longer runs (or unreadable): taken over.
                        _ => {
                            let _ = std::fs::remove_file(&path);
                        }
                    }
                }
                Err(e) => return Err(io(&path, e)),
            }
        }
        Err(io(&path, "could not be created"))
    }
}

impl RunLock {
    /// For a command that reads `run` and writes to `out`: the run's lock when `out` lies inside
    /// the run (a read-only run can still be read into a folder elsewhere); otherwise no lock,
    /// but a refusal while another process works in the run (its checkpoint may be half
    /// swapped).
    pub fn for_output(run: &Path, out: &Path, command: &str) -> Result<Option<Self>, FitError> {
        let inside = match (resolved(run), resolved(out)) {
            (Some(run), Some(out)) => out.starts_with(run),
            _ => true,
        };
        if inside {
            return Self::acquire(run, command).map(Some);
        }
        if let Some((pid, what)) = holder(run).filter(|(pid, _)| *pid != std::process::id() && !process_is_gone(*pid)) {
            return Err(io(run, format!("another umbra {what} (process {pid}) is working in this run folder; wait for it to finish")));
        }
        Ok(None)
    }
}

/// `path` absolute with its links resolved, also when it does not exist yet: its nearest
/// existing ancestor resolved, the rest appended (so a folder about to be made inside a run
/// reached through a link is still seen inside it).
fn resolved(path: &Path) -> Option<PathBuf> {
    let absolute = std::path::absolute(path).ok()?;
    let mut rest = Vec::new();
    let mut at = absolute.as_path();
    loop {
        if let Ok(real) = std::fs::canonicalize(at) {
            return Some(rest.iter().rev().fold(real, |p, c| p.join(c)));
        }
        rest.push(at.file_name()?.to_os_string());
        at = at.parent()?;
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// The process id and command a lock file names, if it is readable.
fn holder(run: &Path) -> Option<(u32, String)> {
    let text = std::fs::read_to_string(run.join(LOCK_FILE)).ok()?;
    let mut words = text.split_whitespace();
    let pid = words.next()?.parse().ok()?;
    Some((pid, words.next().unwrap_or("umbra").to_string()))
}

/// Whether another live process holds `run`'s lock.
pub fn held_elsewhere(run: &Path) -> bool {
    holder(run).is_some_and(|(pid, _)| pid != std::process::id() && !process_is_gone(pid))
}

/// Whether process `pid` has certainly exited. Known only where `/proc` lists processes
/// (Linux); elsewhere a lock is never assumed stale.
fn process_is_gone(pid: u32) -> bool {
    Path::new("/proc/self").exists() && !Path::new(&format!("/proc/{pid}")).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    #[test]
    fn an_output_inside_a_run_reached_through_a_link_takes_the_runs_lock() {
        let dir = std::env::temp_dir().join(format!("umbra-lock-{}", std::process::id()));
        let run = dir.join("run");
        std::fs::create_dir_all(&run).unwrap();
        let link = dir.join("link");
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(&run, &link).unwrap();
        // The output, not yet made, named through the link; the run by its own path, and the
        // other way round.
        for (named_run, out) in [(&run, link.join("relit/sun")), (&link, run.join("relit/sun"))] {
            let lock = RunLock::for_output(named_run, &out, "relight").unwrap();
            assert!(lock.is_some() && run.join(LOCK_FILE).is_file(), "written into the run: locked ({})", out.display());
        }
        let elsewhere = RunLock::for_output(&link, &dir.join("out/sun"), "relight").unwrap();
        assert!(elsewhere.is_none() && !run.join(LOCK_FILE).exists(), "written elsewhere: no lock");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
