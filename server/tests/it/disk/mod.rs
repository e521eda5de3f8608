//! A disk in memory for recording tests: [`Disk`] is a `RecordFiles` whose files live in a
//! shared list, and which fails (like a full disk: `StorageFull`) once a budget of bytes is
//! spent, part-way through a write if the budget ends there, or once a number of files has
//! been created. The tests hand it to the real `WorldCore` and world loop and read the
//! files back.
#![allow(dead_code)] // each test file uses its own subset

use std::io::{self, Write};
use std::sync::{Arc, Mutex, MutexGuard};

use roam_protocol::sync::lock;
use roam_server::sim::record_files::{RecordFile, RecordFiles};

#[derive(Default)]
struct State {
    /// Every file created and not removed: its name and bytes.
    files: Vec<(String, Vec<u8>)>,
    created: usize,
    /// Bytes the disk still takes (`None`: no limit).
    left: Option<u64>,
    /// Files it still creates (`None`: no limit).
    creates_left: Option<usize>,
    /// Writes refused so far.
    refused: u32,
}

/// The disk; clones share it.
#[derive(Clone, Default)]
pub struct Disk(Arc<Mutex<State>>);

impl Disk {
    /// A disk that takes `bytes` bytes in all (across files), then fails.
    pub fn failing_after(bytes: u64) -> Disk {
        let d = Disk::default();
        d.state().left = Some(bytes);
        d
    }

    /// A disk that creates `n` files, then refuses.
    pub fn creating(n: usize) -> Disk {
        let d = Disk::default();
        d.state().creates_left = Some(n);
        d
    }

    fn state(&self) -> MutexGuard<'_, State> {
        lock(&self.0)
    }

    /// The files (name and bytes), in the order they were created.
    pub fn files(&self) -> Vec<(String, Vec<u8>)> {
        self.state().files.clone()
    }

    /// Bytes of every file together.
    pub fn total(&self) -> u64 {
        self.state().files.iter().map(|(_, b)| b.len() as u64).sum()
    }

    /// Writes refused so far.
    pub fn refused(&self) -> u32 {
        self.state().refused
    }
}

struct MemFile {
    disk: Disk,
    name: String,
}

impl MemFile {
    fn bytes<'a>(&self, s: &'a mut State) -> io::Result<&'a mut Vec<u8>> {
        s.files
            .iter_mut()
            .find(|(n, _)| *n == self.name)
            .map(|(_, b)| b)
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "the file was removed"))
    }
}

impl Write for MemFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let mut s = self.disk.state();
        let n = match s.left {
            None => buf.len(),
            Some(0) if !buf.is_empty() => {
                s.refused += 1;
                return Err(io::Error::new(
                    io::ErrorKind::StorageFull,
                    "no space left on the test disk",
                ));
            }
            Some(left) => buf.len().min(usize::try_from(left).unwrap_or(usize::MAX)),
        };
        if let Some(left) = &mut s.left {
            *left -= n as u64;
        }
        self.bytes(&mut s)?.extend_from_slice(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

impl RecordFile for MemFile {
    fn cut(&mut self, len: u64) -> io::Result<()> {
        let mut s = self.disk.state();
        let bytes = self.bytes(&mut s)?;
        bytes.truncate(usize::try_from(len).unwrap_or(usize::MAX));
        Ok(())
    }
}

impl RecordFiles for Disk {
    fn create(&mut self) -> io::Result<(String, Box<dyn RecordFile>)> {
        let mut s = self.state();
        if s.creates_left == Some(0) {
            return Err(io::Error::new(
                io::ErrorKind::PermissionDenied,
                "creating a file on the test disk: refused",
            ));
        }
        if let Some(n) = &mut s.creates_left {
            *n -= 1;
        }
        s.created += 1;
        let name = format!("mem-{:03}.rec", s.created);
        s.files.push((name.clone(), Vec::new()));
        let file = MemFile {
            disk: self.clone(),
            name: name.clone(),
        };
        Ok((name, Box::new(file)))
    }

    fn remove(&mut self, name: &str) -> io::Result<()> {
        let mut s = self.state();
        let at =
            s.files.iter().position(|(n, _)| n == name).ok_or_else(|| {
                io::Error::new(io::ErrorKind::NotFound, format!("no file {name}"))
            })?;
        s.files.remove(at);
        Ok(())
    }
}
