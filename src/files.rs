//! Bounded reads of the text files a user names (scenes, schedules, lights, checkpoint state):
//! only regular files, and none larger than its kind allows, so a link to `/dev/zero`, a FIFO
//! or a runaway file is refused with a message instead of being read until memory runs out.

use std::io::Read;
use std::path::{Path, PathBuf};

/// The largest `scene.json` read: a 10,000-image, 2,000-frame, 60-bone capture takes about
/// 30 MB of JSON; parsing costs about 20 bytes of memory per byte of text.
pub const SCENE_BYTES: u64 = 64 << 20;

/// The largest schedule or light file read (a schedule is a few kilobytes).
pub const SMALL_TEXT_BYTES: u64 = 1 << 20;

/// The largest checkpoint `state.json` read (its error maps grow with the training views:
/// about 3 KB each).
pub const STATE_BYTES: u64 = 256 << 20;

/// Reads `path` as UTF-8 text when it is a regular file of at most `limit` bytes. The error
/// says what is wrong without the path (callers name the file).
pub fn read_text(path: &Path, limit: u64) -> std::io::Result<String> {
    use std::io::{Error, ErrorKind};
    let meta = std::fs::metadata(path).map_err(|e| if e.kind() == ErrorKind::NotFound { Error::new(ErrorKind::NotFound, "file not found") } else { e })?;
    if meta.is_dir() {
        return Err(Error::new(ErrorKind::InvalidInput, "is a folder, not a file"));
    }
    if !meta.is_file() {
        return Err(Error::new(ErrorKind::InvalidInput, "is not a regular file (a device, FIFO or socket): name a file"));
    }
    if meta.len() > limit {
        return Err(Error::new(ErrorKind::InvalidInput, format!("is {} bytes, more than the {limit} allowed", meta.len())));
    }
    // The file may grow between the check and the read: read one byte past the limit at most.
    let mut text = String::new();
    std::fs::File::open(path)?.take(limit + 1).read_to_string(&mut text)?;
    if text.len() as u64 > limit {
        return Err(Error::new(ErrorKind::InvalidInput, format!("is more than the {limit} bytes allowed")));
    }
    Ok(text)
}

/// A file created beside `path` under a hidden name of its own (`.NAME.TAG-PID-N`), made
/// exclusively: never a file that was there before, whoever put it there.
pub fn create_new_beside(path: &Path, tag: &str) -> std::io::Result<(PathBuf, std::fs::File)> {
    new_beside(path, tag, |p| std::fs::OpenOptions::new().write(true).create_new(true).open(p))
}

/// A folder created beside `path` under a hidden name of its own (`.NAME.TAG-PID-N`), made
/// exclusively: the caller owns it and everything in it, and may remove it.
pub fn create_folder_beside(path: &Path, tag: &str) -> std::io::Result<PathBuf> {
    new_beside(path, tag, |p| std::fs::create_dir(p)).map(|(p, ())| p)
}

/// The first free `.NAME.TAG-PID-N` beside `path` that `make` creates.
fn new_beside<T>(path: &Path, tag: &str, make: impl Fn(&Path) -> std::io::Result<T>) -> std::io::Result<(PathBuf, T)> {
    use std::io::{Error, ErrorKind};
    let name = path.file_name().ok_or_else(|| Error::new(ErrorKind::InvalidInput, "names no file or folder (it ends in '.', '..' or '/')"))?;
    for n in 0..1000 {
        let candidate = path.with_file_name(format!(".{}.{tag}-{}-{n}", name.to_string_lossy(), std::process::id()));
        match make(&candidate) {
            Ok(made) => return Ok((candidate, made)),
            Err(e) if e.kind() == ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    Err(Error::new(ErrorKind::AlreadyExists, "no free temporary name beside it"))
}

/// `path` made absolute with its last part kept as named (`.`, `..` resolved through the
/// folders that exist): what a command writes to when it is given `--out .` or `--out ..`.
pub fn absolute_target(path: &Path) -> std::io::Result<PathBuf> {
    match path.file_name() {
        Some(_) if !path.exists() => {
            let parent = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
            Ok(std::fs::canonicalize(parent)?.join(path.file_name().unwrap_or_default()))
        }
        _ => std::fs::canonicalize(path),
    }
}

/// The most memory this process has held at once (its peak resident set, `VmHWM` in
/// `/proc/self/status`), in bytes; `None` where the system does not say (not Linux).
pub fn peak_memory_bytes() -> Option<u64> {
    let status = read_text(Path::new("/proc/self/status"), SMALL_TEXT_BYTES).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_folders_devices_and_oversized_files_and_reads_the_rest() {
        let dir = std::env::temp_dir().join(format!("umbra-files-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("a.json");
        std::fs::write(&file, "{\"a\": 1}").unwrap();
        assert_eq!(read_text(&file, 100).unwrap(), "{\"a\": 1}");
        assert!(read_text(&file, 3).unwrap_err().to_string().contains("more than the 3"));
        assert!(read_text(&dir, 100).unwrap_err().to_string().contains("is a folder"));
        assert!(read_text(&dir.join("missing"), 100).unwrap_err().to_string().contains("not found"));
        if Path::new("/dev/zero").exists() {
            assert!(read_text(Path::new("/dev/zero"), 100).unwrap_err().to_string().contains("not a regular file"));
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_new_name_beside_a_path_never_takes_one_that_is_there() {
        let dir = std::env::temp_dir().join(format!("umbra-files-beside-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let target = dir.join("scene");
        let taken = dir.join(format!(".scene.importing-{}-0", std::process::id()));
        std::fs::create_dir_all(&taken).unwrap();
        std::fs::write(taken.join("keep.txt"), "keep").unwrap();
        let made = create_folder_beside(&target, "importing").unwrap();
        assert_ne!(made, taken);
        assert_eq!(std::fs::read_to_string(taken.join("keep.txt")).unwrap(), "keep");
        let (file, _) = create_new_beside(&target, "importing").unwrap();
        assert!(file != taken && file != made);
        assert!(create_folder_beside(Path::new("/"), "x").is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
