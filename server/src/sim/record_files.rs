//! Where the server's recording files come from: [`RecordFiles`] opens the next file of a
//! session and [`RecordFile`] is one, written and cut back after a failure. [`RecordDir`]
//! is the real one (files in a directory); tests put a writer that fails after N bytes in
//! its place, and drive the real world loop with it.
//!
//! **Names that never collide and sort by time:**
//! `session-YYYYMMDD-HHMMSS-<pid>-<n>.rec`, the date and time in UTC (computed here from the
//! Unix time: no calendar crate for one formula), the process id, and a counter of this
//! directory's files (four digits at least, so that a session's files sort in order even
//! within one second). Files are created with `create_new`: a name already taken (another
//! server, or the same one started twice in a second) moves on to the next counter, never
//! overwrites. The clock is passed in (`fn() -> u64`, Unix seconds): this module is part of
//! the simulation, which reads no clock itself, and tests give a fixed one.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use roam_protocol::sync::lock;

/// One recording file: written at record boundaries, and cut back to its last whole record
/// when a write fails.
pub trait RecordFile: Write + Send {
    /// Cuts the file back to its first `len` bytes. A file shorter than that is left as it
    /// is (a cut never lengthens a file).
    fn cut(&mut self, len: u64) -> io::Result<()>;
}

impl RecordFile for File {
    fn cut(&mut self, len: u64) -> io::Result<()> {
        if self.metadata()?.len() > len {
            self.set_len(len)?;
        }
        Ok(())
    }
}

/// Where a session's recording files come from, one after another (a new one at each
/// rotation).
pub trait RecordFiles: Send {
    /// Creates the next file, new and empty (never one that exists): its name, for logs,
    /// and the file. An error names the file or the place it would have been.
    fn create(&mut self) -> io::Result<(String, Box<dyn RecordFile>)>;

    /// Removes a file [`RecordFiles::create`] made that holds not even a whole header (a
    /// write failed inside it): no file the server leaves is one `replay` refuses.
    fn remove(&mut self, name: &str) -> io::Result<()>;
}

/// Tries at most this many names per file before giving up.
const MAX_TRIES: u32 = 10_000;

/// Recording files in a directory (which must exist), named by time (see the module docs).
pub struct RecordDir {
    dir: PathBuf,
    pid: u32,
    clock: fn() -> u64,
    next: u32,
    made: MadeFiles,
}

/// The files a [`RecordDir`] has created, in order: a handle the command line keeps to
/// name them, while the directory itself is the world thread's.
#[derive(Clone, Debug, Default)]
pub struct MadeFiles(Arc<Mutex<Vec<PathBuf>>>);

impl MadeFiles {
    pub fn list(&self) -> Vec<PathBuf> {
        lock(&self.0).clone()
    }

    fn push(&self, path: PathBuf) {
        lock(&self.0).push(path);
    }

    /// Takes the file named `name` off the list, and returns its path.
    fn forget(&self, name: &str) -> Option<PathBuf> {
        let mut l = lock(&self.0);
        let at = l.iter().rposition(|p| p.display().to_string() == name)?;
        Some(l.remove(at))
    }
}

impl RecordDir {
    /// Files in `dir`, named from `clock` (Unix seconds) and this process's id.
    pub fn new(dir: impl Into<PathBuf>, clock: fn() -> u64) -> RecordDir {
        RecordDir {
            dir: dir.into(),
            pid: std::process::id(),
            clock,
            next: 0,
            made: MadeFiles::default(),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// A handle on the list of files this directory creates.
    pub fn made(&self) -> MadeFiles {
        self.made.clone()
    }
}

impl RecordFiles for RecordDir {
    fn create(&mut self) -> io::Result<(String, Box<dyn RecordFile>)> {
        let now = (self.clock)();
        for _ in 0..MAX_TRIES {
            let path = self.dir.join(file_name(now, self.pid, self.next));
            self.next = self.next.wrapping_add(1);
            match OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(file) => {
                    self.made.push(path.clone());
                    return Ok((path.display().to_string(), Box::new(file)));
                }
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                Err(e) => {
                    return Err(io::Error::new(
                        e.kind(),
                        format!("creating {}: {e}", path.display()),
                    ));
                }
            }
        }
        Err(io::Error::new(
            io::ErrorKind::AlreadyExists,
            format!(
                "no free recording file name in {} after {MAX_TRIES} tries",
                self.dir.display()
            ),
        ))
    }

    fn remove(&mut self, name: &str) -> io::Result<()> {
        let path = self
            .made
            .forget(name)
            .unwrap_or_else(|| PathBuf::from(name));
        std::fs::remove_file(&path)
            .map_err(|e| io::Error::new(e.kind(), format!("removing {name}: {e}")))
    }
}

/// `session-YYYYMMDD-HHMMSS-<pid>-<n>.rec` for `unix` seconds (UTC).
pub fn file_name(unix: u64, pid: u32, n: u32) -> String {
    let (days, secs) = (unix / 86_400, unix % 86_400);
    let (y, m, d) = civil_from_days(days);
    format!(
        "session-{y:04}{m:02}{d:02}-{:02}{:02}{:02}-{pid}-{n:04}.rec",
        secs / 3600,
        secs / 60 % 60,
        secs % 60
    )
}

/// The (year, month, day) of a count of days since 1970-01-01 (Howard Hinnant's
/// `civil_from_days`, for days on and after the epoch).
fn civil_from_days(days: u64) -> (u64, u64, u64) {
    let z = days + 719_468;
    let era = z / 146_097;
    let doe = z % 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + u64::from(m <= 2);
    (y, m, d)
}

#[cfg(test)]
mod tests {
    use super::file_name;

    #[test]
    fn names_give_the_utc_date_and_time() {
        assert_eq!(file_name(0, 7, 0), "session-19700101-000000-7-0000.rec");
        // A leap day, a year's last second, and an ordinary moment.
        assert_eq!(
            file_name(951_782_400, 7, 1),
            "session-20000229-000000-7-0001.rec"
        );
        assert_eq!(
            file_name(1_704_067_199, 7, 2),
            "session-20231231-235959-7-0002.rec"
        );
        assert_eq!(
            file_name(1_700_000_000, 123, 12_345),
            "session-20231114-221320-123-12345.rec"
        );
        assert_eq!(
            file_name(4_102_444_800, 1, 0),
            "session-21000101-000000-1-0000.rec"
        );
    }

    #[test]
    fn names_sort_by_time() {
        let times = [0, 59, 60, 3_599, 86_399, 86_400, 951_782_400, 1_700_000_000];
        let names: Vec<String> = times.iter().map(|&t| file_name(t, 42, 0)).collect();
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        let counted: Vec<String> = (0..12).map(|n| file_name(5, 42, n)).collect();
        let mut sorted = counted.clone();
        sorted.sort();
        assert_eq!(counted, sorted);
    }
}
