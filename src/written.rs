//! The record of what a command wrote into a folder a user named (`render --motion --out DIR`,
//! `relight --out DIR`): a manifest, `.umbra-written.json`, naming the command and every file
//! it wrote. A later run of the same command replaces only the files listed there; a folder that
//! holds anything without such a manifest, or a file in the way that the manifest does not
//! list, is refused before anything is written. A user's folder cannot carry the manifest by
//! accident, where it could a file named `sheet.png` or `animation.png`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The manifest's file name in the folder.
pub const MANIFEST: &str = ".umbra-written.json";

/// The manifest's format tag.
const FORMAT: &str = "umbra-written/1";

#[derive(Serialize, Deserialize)]
struct Manifest {
    format: String,
    command: String,
    files: BTreeSet<String>,
}

/// A folder a command may write into: new, empty, or written before by the same command.
#[derive(Debug)]
pub struct OutputFolder {
    dir: PathBuf,
    command: String,
    /// What an earlier run of the command wrote there (and may be replaced or removed).
    earlier: BTreeSet<String>,
}

/// Whether `name` is one plain file name a command writes (no separator, not hidden): a
/// manifest edited to list `../x` or the manifest itself lists nothing.
fn plain(name: &str) -> bool {
    !name.is_empty() && !name.starts_with('.') && !name.contains(['/', '\\']) && name != MANIFEST
}

impl OutputFolder {
    /// Claims `dir` for `command` (as the user would type it, `render --motion`) to write the
    /// files `planned`; refused, with the folder or the file in the way named, when `dir` is a
    /// file, holds anything without this command's manifest, or holds a planned file that the
    /// manifest does not list.
    pub fn claim(dir: &Path, command: &str, planned: &[String]) -> Result<OutputFolder, String> {
        let say = |p: &Path, what: String| format!("{}: {what} (nothing was written)", p.display());
        if std::fs::symlink_metadata(dir).is_ok() && !dir.is_dir() {
            return Err(say(dir, "exists and is not a folder: --out names a folder".into()));
        }
        let holds_files = std::fs::read_dir(dir).is_ok_and(|mut entries| entries.next().is_some());
        let earlier = match holds_files {
            false => BTreeSet::new(),
            true => match read_manifest(&dir.join(MANIFEST)) {
                Some(m) if m.command == command => m.files.into_iter().filter(|n| plain(n)).collect(),
                Some(m) => return Err(say(dir, format!("holds what `umbra {}` wrote: choose another --out folder for `umbra {command}`", m.command))),
                None => return Err(say(dir, format!("holds files but no {MANIFEST} of an earlier `umbra {command}`: choose a new or empty --out folder"))),
            },
        };
        for name in planned {
            let path = dir.join(name);
            if std::fs::symlink_metadata(&path).is_ok() && !earlier.contains(name) {
                return Err(say(&path, format!("is in the way and was not written by `umbra {command}`: move it or choose another --out folder")));
            }
        }
        Ok(OutputFolder { dir: dir.to_path_buf(), command: command.to_string(), earlier })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Creates the folder and records, before any of them is written, the files `planned`
    /// together with the earlier run's: an interrupted run leaves a manifest that covers all it
    /// may have written.
    pub fn begin(&self, planned: &[String]) -> std::io::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let all: BTreeSet<String> = self.earlier.iter().cloned().chain(planned.iter().cloned()).collect();
        self.write_manifest(all)
    }

    /// Ends the run that wrote `written`: the earlier run's files it did not write again are
    /// removed (they describe another render), and the manifest lists just `written`.
    pub fn finish(&self, written: &[String]) -> std::io::Result<()> {
        let now: BTreeSet<String> = written.iter().cloned().collect();
        for stale in self.earlier.difference(&now) {
            let path = self.dir.join(stale);
            if std::fs::symlink_metadata(&path).is_ok_and(|m| m.is_file()) {
                std::fs::remove_file(&path)?;
            }
        }
        self.write_manifest(now)
    }

    fn write_manifest(&self, files: BTreeSet<String>) -> std::io::Result<()> {
        let manifest = Manifest { format: FORMAT.into(), command: self.command.clone(), files };
        let text = serde_json::to_string_pretty(&manifest).map_err(std::io::Error::other)?;
        crate::imageio::write_atomic(&self.dir.join(MANIFEST), text.as_bytes())
    }
}

/// The manifest at `path`, when it is one (a regular file of this format).
fn read_manifest(path: &Path) -> Option<Manifest> {
    let text = crate::files::read_text(path, crate::files::SMALL_TEXT_BYTES).ok()?;
    let manifest: Manifest = serde_json::from_str(&text).ok()?;
    (manifest.format == FORMAT).then_some(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_folder_is_written_again_only_by_the_command_that_wrote_it_and_only_its_files() {
        let dir = std::env::temp_dir().join(format!("umbra-written-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let out = dir.join("out");
        let first = OutputFolder::claim(&out, "relight", &names(&["a.png", "b.png"])).unwrap();
        first.begin(&names(&["a.png", "b.png"])).unwrap();
        std::fs::write(out.join("a.png"), "1").unwrap();
        std::fs::write(out.join("b.png"), "1").unwrap();
        first.finish(&names(&["a.png", "b.png"])).unwrap();
        // A user's file beside them stays; one in the way of a new name is refused.
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        std::fs::write(out.join("c.png"), "mine").unwrap();
        assert!(OutputFolder::claim(&out, "relight", &names(&["a.png", "c.png"])).unwrap_err().contains("c.png"));
        assert!(OutputFolder::claim(&out, "render --motion", &names(&["a.png"])).unwrap_err().contains("umbra relight"));
        // Written again with fewer files: the stale one goes, the user's stay.
        let again = OutputFolder::claim(&out, "relight", &names(&["a.png"])).unwrap();
        again.begin(&names(&["a.png"])).unwrap();
        again.finish(&names(&["a.png"])).unwrap();
        assert!(!out.join("b.png").exists() && out.join("a.png").exists());
        assert_eq!(std::fs::read_to_string(out.join("notes.txt")).unwrap(), "mine");
        assert_eq!(std::fs::read_to_string(out.join("c.png")).unwrap(), "mine");
        // A folder of the user's with the old marks of a render but no manifest is refused.
        let user = dir.join("user");
        std::fs::create_dir_all(&user).unwrap();
        std::fs::write(user.join("sheet.png"), "mine").unwrap();
        assert!(OutputFolder::claim(&user, "relight", &names(&["x.png"])).unwrap_err().contains(MANIFEST));
        // A manifest edited to list a path outside the folder removes nothing there.
        std::fs::write(dir.join("outside.png"), "mine").unwrap();
        std::fs::write(out.join(MANIFEST), r#"{"format":"umbra-written/1","command":"relight","files":["a.png","../outside.png"]}"#).unwrap();
        OutputFolder::claim(&out, "relight", &names(&["a.png"])).unwrap().finish(&names(&["a.png"])).unwrap();
        assert!(dir.join("outside.png").exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
