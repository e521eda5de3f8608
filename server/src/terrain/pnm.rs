//! Binary Netpbm images: PGM `P5` heightfields and PPM `P6` colour maps.
//!
//! Readers stream from a [`BufReader`] and trust nothing: the header is parsed token by token
//! (comments and any whitespace between tokens allowed, exactly one whitespace byte after
//! maxval), every number is range-checked, and the declared data size is compared with the
//! file's length *before* anything is allocated, so a header that promises gigabytes on a
//! 1 KB file is an error, not an allocation. Truncated data and trailing bytes are errors.
//!
//! Errors name the field (`magic`, `width`, `height`, `maxval`, `data`) and what was expected;
//! the caller adds the file name (see [`crate::terrain::data_error::DataError`]).

use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Read, Write};
use std::path::Path;

use crate::terrain::heightfield::{Heightfield, MAX_LEVELS, levels_of_side};

/// Bytes read between two progress reports.
const PROGRESS_STEP: u64 = 4 << 20;
/// Bytes converted per read while streaming samples.
const CHUNK: usize = 64 << 10;
/// Longest number token accepted in a header: 9 digits (below 10^9), far beyond any valid size.
const MAX_DIGITS: usize = 9;

/// Why an image was rejected.
#[derive(Debug, thiserror::Error)]
pub enum PnmError {
    /// The content is malformed: `field` is the header field or `data`, `message` says what
    /// was expected and what was found.
    #[error("{field}: {message}")]
    Format {
        /// `magic`, `width`, `height`, `maxval` or `data`.
        field: &'static str,
        /// "expected …, got …".
        message: String,
    },
    /// The file could not be opened or read.
    #[error("cannot {action}: {error}")]
    Io {
        /// What failed: `open`, `read`, `stat`.
        action: &'static str,
        /// The operating system's error.
        error: io::Error,
    },
}

fn format_err(field: &'static str, message: impl Into<String>) -> PnmError {
    PnmError::Format {
        field,
        message: message.into(),
    }
}

fn io_err(action: &'static str) -> impl FnOnce(io::Error) -> PnmError {
    move |error| PnmError::Io { action, error }
}

/// The two Netpbm formats used by data sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// `P5`: binary greymap.
    Pgm,
    /// `P6`: binary RGB pixmap.
    Ppm,
}

impl Kind {
    fn magic(self) -> &'static str {
        match self {
            Kind::Pgm => "P5",
            Kind::Ppm => "P6",
        }
    }
}

/// A parsed, not yet validated header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    /// Image format.
    pub kind: Kind,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Largest sample value, 1 ..= 65535.
    pub maxval: u16,
    /// Bytes before the first sample.
    pub data_offset: u64,
}

impl Header {
    /// Bytes per sample: 1 when `maxval < 256`, else 2 (big-endian).
    pub fn bytes_per_sample(&self) -> u64 {
        if self.maxval < 256 { 1 } else { 2 }
    }

    /// Samples per pixel: 1 for PGM, 3 for PPM.
    pub fn channels(&self) -> u64 {
        match self.kind {
            Kind::Pgm => 1,
            Kind::Ppm => 3,
        }
    }

    /// Exact byte length of the raster this header declares (cannot overflow: both sides
    /// are below 10^9).
    pub fn data_len(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height) * self.channels() * self.bytes_per_sample()
    }
}

/// Counts bytes consumed from the wrapped reader, for `data_offset` and progress.
struct Counting<R> {
    inner: R,
    consumed: u64,
}

impl<R: BufRead> Counting<R> {
    /// Consume one byte that `peek` has just returned.
    fn advance(&mut self) {
        self.inner.consume(1);
        self.consumed += 1;
    }

    fn peek(&mut self) -> Result<Option<u8>, PnmError> {
        let buf = self.inner.fill_buf().map_err(io_err("read"))?;
        Ok(buf.first().copied())
    }
}

fn is_space(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | b'\n' | b'\r' | 0x0b | 0x0c)
}

fn describe(b: u8) -> String {
    if b.is_ascii_graphic() {
        format!("'{}'", b as char)
    } else {
        format!("byte 0x{b:02x}")
    }
}

/// Skip whitespace and `#` comments before a header token.
fn skip_space<R: BufRead>(r: &mut Counting<R>) -> Result<(), PnmError> {
    loop {
        match r.peek()? {
            Some(b) if is_space(b) => {
                r.advance();
            }
            Some(b'#') => loop {
                match r.peek()? {
                    None | Some(b'\n') | Some(b'\r') => break,
                    Some(_) => {
                        r.advance();
                    }
                }
            },
            _ => return Ok(()),
        }
    }
}

/// Read one decimal header number after optional whitespace and comments. The byte that
/// ends it is left unread.
fn number<R: BufRead>(
    r: &mut Counting<R>,
    field: &'static str,
    expected: &str,
) -> Result<u32, PnmError> {
    skip_space(r)?;
    let mut n: u32 = 0;
    let mut digits = 0;
    loop {
        let next = r.peek()?;
        match next {
            Some(b) if b.is_ascii_digit() => {
                if digits == MAX_DIGITS {
                    return Err(format_err(
                        field,
                        format!(
                            "expected {expected}, got a number of more than {MAX_DIGITS} digits"
                        ),
                    ));
                }
                r.advance();
                // At most 9 digits: always fits in u32.
                n = n * 10 + u32::from(b - b'0');
                digits += 1;
            }
            _ if digits > 0 => return Ok(n),
            Some(b) => {
                return Err(format_err(
                    field,
                    format!(
                        "expected {expected} (a decimal number), got {}",
                        describe(b)
                    ),
                ));
            }
            None => {
                return Err(format_err(
                    field,
                    format!("expected {expected}, got end of file"),
                ));
            }
        }
    }
}

/// Parse a header of the given kind. On success the reader stands on the first data byte.
fn read_header<R: BufRead>(
    r: &mut Counting<R>,
    kind: Kind,
    side_hint: &str,
) -> Result<Header, PnmError> {
    let magic = kind.magic();
    let want = format!(
        "\"{magic}\" (binary {})",
        match kind {
            Kind::Pgm => "PGM",
            Kind::Ppm => "PPM",
        }
    );
    let mut got = Vec::with_capacity(2);
    for _ in 0..2 {
        match r.peek()? {
            Some(b) => {
                got.push(b);
                r.advance();
            }
            None => break,
        }
    }
    if got != magic.as_bytes() {
        return Err(format_err(
            "magic",
            format!("expected {want}, got {:?}", String::from_utf8_lossy(&got)),
        ));
    }
    let maxval_hint = match kind {
        Kind::Pgm => "1 ..= 65535",
        Kind::Ppm => "255",
    };
    // Each token must be separated from the previous one by whitespace or a comment.
    let fields = [
        ("width", side_hint),
        ("height", side_hint),
        ("maxval", maxval_hint),
    ];
    let mut values = [0u32; 3];
    let mut previous = "magic";
    for (slot, (field, hint)) in values.iter_mut().zip(fields) {
        match r.peek()? {
            Some(b) if is_space(b) || b == b'#' => {}
            Some(b) => {
                return Err(format_err(
                    previous,
                    format!("expected whitespace after {previous}, got {}", describe(b)),
                ));
            }
            None => {
                return Err(format_err(
                    field,
                    format!("expected {hint}, got end of file"),
                ));
            }
        }
        *slot = number(r, field, hint)?;
        previous = field;
    }
    let [width, height, maxval] = values;
    match r.peek()? {
        Some(b) if is_space(b) => {
            r.advance();
        }
        Some(b) => {
            return Err(format_err(
                "maxval",
                format!(
                    "expected a single whitespace byte after maxval, got {}",
                    describe(b)
                ),
            ));
        }
        None => {
            return Err(format_err(
                "maxval",
                "expected a single whitespace byte after maxval, got end of file",
            ));
        }
    }
    let maxval = match u16::try_from(maxval) {
        Ok(m) if m >= 1 => m,
        _ => {
            return Err(format_err(
                "maxval",
                format!("expected {maxval_hint}, got {maxval}"),
            ));
        }
    };
    Ok(Header {
        kind,
        width,
        height,
        maxval,
        data_offset: r.consumed,
    })
}

/// Compare the declared raster size with what the file holds after the header.
fn check_length(header: &Header, file_len: u64) -> Result<(), PnmError> {
    let want = header.data_len();
    let have = file_len.saturating_sub(header.data_offset);
    let what = format!(
        "{} × {} × {} byte{}",
        header.width,
        header.height,
        header.channels() * header.bytes_per_sample(),
        if header.channels() * header.bytes_per_sample() == 1 {
            ""
        } else {
            "s"
        }
    );
    if have < want {
        return Err(format_err(
            "data",
            format!("expected {want} bytes ({what}), got {have}: the file is truncated"),
        ));
    }
    if have > want {
        return Err(format_err(
            "data",
            format!(
                "expected {want} bytes ({what}), got {have}: {} trailing bytes",
                have - want
            ),
        ));
    }
    Ok(())
}

/// An opened image whose header has been parsed; the raster is read by `read_*`.
struct Opened {
    reader: Counting<BufReader<File>>,
    header: Header,
    file_len: u64,
}

fn open(path: &Path, kind: Kind, side_hint: &str) -> Result<Opened, PnmError> {
    let file = File::open(path).map_err(io_err("open"))?;
    let meta = file.metadata().map_err(io_err("stat"))?;
    if !meta.is_file() {
        return Err(PnmError::Io {
            action: "read",
            error: io::Error::new(io::ErrorKind::InvalidInput, "not a regular file"),
        });
    }
    let mut reader = Counting {
        inner: BufReader::with_capacity(CHUNK, file),
        consumed: 0,
    };
    let header = read_header(&mut reader, kind, side_hint)?;
    Ok(Opened {
        reader,
        header,
        file_len: meta.len(),
    })
}

impl Opened {
    /// Fill `buf` completely; a short read means the file shrank after `check_length`.
    fn fill(&mut self, buf: &mut [u8]) -> Result<(), PnmError> {
        self.reader.inner.read_exact(buf).map_err(|e| {
            if e.kind() == io::ErrorKind::UnexpectedEof {
                format_err(
                    "data",
                    format!(
                        "expected {} bytes, got fewer: the file is truncated",
                        self.header.data_len()
                    ),
                )
            } else {
                PnmError::Io {
                    action: "read",
                    error: e,
                }
            }
        })?;
        self.reader.consumed += buf.len() as u64;
        Ok(())
    }

    /// After the raster: the file must end here.
    fn expect_end(&mut self) -> Result<(), PnmError> {
        if self.reader.peek()?.is_some() {
            return Err(format_err(
                "data",
                format!(
                    "expected {} bytes, got more: trailing bytes after the raster",
                    self.header.data_len()
                ),
            ));
        }
        Ok(())
    }

    fn report(&self, last: &mut u64, progress: &mut dyn FnMut(u64)) {
        if self.reader.consumed - *last >= PROGRESS_STEP {
            *last = self.reader.consumed;
            progress(self.reader.consumed);
        }
    }
}

/// Check a PGM header without reading the raster: magic `P5`, square, side `2^N + 1`,
/// maxval in 1 ..= 65535 and the exact data length. Returns the header.
pub fn read_pgm_header(path: &Path) -> Result<Header, PnmError> {
    Ok(open_pgm(path)?.header)
}

fn side_hint() -> String {
    format!("2^N + 1 (3, 5, 9, …, {})", (1u32 << MAX_LEVELS) + 1)
}

fn open_pgm(path: &Path) -> Result<Opened, PnmError> {
    let hint = side_hint();
    let opened = open(path, Kind::Pgm, &hint)?;
    let h = opened.header;
    if levels_of_side(u64::from(h.width)).is_none() {
        return Err(format_err(
            "width",
            format!("expected {hint}, got {}", h.width),
        ));
    }
    if h.height != h.width {
        return Err(format_err(
            "height",
            format!(
                "expected {} (the heightfield must be square: height = width), got {}",
                h.width, h.height
            ),
        ));
    }
    check_length(&h, opened.file_len)?;
    Ok(opened)
}

/// Read a heightfield from a binary PGM. 8-bit samples are stored as they are; 16-bit ones
/// are big-endian. Every sample must be ≤ maxval. `progress` receives the bytes read so far
/// (every few MB and at the end).
pub fn read_pgm(path: &Path, progress: &mut dyn FnMut(u64)) -> Result<Heightfield, PnmError> {
    let mut f = open_pgm(path)?;
    let h = f.header;
    let side = h.width;
    let count = u64::from(side) * u64::from(side);
    // Fits: side <= 32769, so count < 2^31.
    let count = usize::try_from(count)
        .map_err(|_| format_err("width", format!("expected at most {}", side_hint())))?;
    let wide = h.bytes_per_sample() == 2;
    let mut samples: Vec<u16> = Vec::new();
    samples
        .try_reserve_exact(count)
        .map_err(|_| format_err("data", format!("cannot allocate {count} samples")))?;
    let mut buf = vec![0u8; CHUNK];
    let mut last = 0;
    let mut left = h.data_len();
    while left > 0 {
        let n = left.min(CHUNK as u64) as usize;
        let chunk = &mut buf[..n];
        f.fill(chunk)?;
        left -= n as u64;
        if wide {
            samples.extend(
                chunk
                    .chunks_exact(2)
                    .map(|p| u16::from_be_bytes([p[0], p[1]])),
            );
        } else {
            samples.extend(chunk.iter().map(|&b| u16::from(b)));
        }
        f.report(&mut last, progress);
    }
    f.expect_end()?;
    progress(f.reader.consumed);
    if let Some(i) = samples.iter().position(|&s| s > h.maxval) {
        return Err(format_err(
            "data",
            format!(
                "expected samples ≤ maxval {}, got {} at row {}, column {}",
                h.maxval,
                samples[i],
                i / side as usize,
                i % side as usize
            ),
        ));
    }
    Heightfield::new(side, samples).map_err(|e| format_err("data", e.to_string()))
}

/// Read an 8-bit RGB PPM of exactly `size × size` pixels (maxval 255), row-major.
/// `progress` receives the bytes read so far.
pub fn read_ppm(
    path: &Path,
    size: u32,
    progress: &mut dyn FnMut(u64),
) -> Result<Vec<[u8; 3]>, PnmError> {
    let mut f = open_ppm(path, size)?;
    let count = usize::try_from(u64::from(size) * u64::from(size))
        .map_err(|_| format_err("width", format!("expected a smaller image, got {size}")))?;
    read_pixels(&mut f, count, progress)
}

/// The `count` RGB pixels after `f`'s header (checked against the file's length before),
/// reserved fallibly and read in chunks, reporting the bytes read; nothing may follow them.
fn read_pixels(
    f: &mut Opened,
    count: usize,
    progress: &mut dyn FnMut(u64),
) -> Result<Vec<[u8; 3]>, PnmError> {
    let mut rgb: Vec<[u8; 3]> = Vec::new();
    rgb.try_reserve_exact(count)
        .map_err(|_| format_err("data", format!("cannot allocate {count} pixels")))?;
    rgb.resize(count, [0; 3]);
    let mut last = 0;
    for chunk in rgb.as_flattened_mut().chunks_mut(CHUNK * 16) {
        f.fill(chunk)?;
        f.report(&mut last, progress);
    }
    f.expect_end()?;
    progress(f.reader.consumed);
    Ok(rgb)
}

/// Check an RGB PPM's header as [`read_ppm`] does (`size × size`, maxval 255, the exact
/// data length) without reading its pixels. Every byte is a valid 8-bit channel, so what
/// `read_ppm` would still refuse is only a file that changes or fails while read.
pub fn read_ppm_header(path: &Path, size: u32) -> Result<Header, PnmError> {
    Ok(open_ppm(path, size)?.header)
}

fn open_ppm(path: &Path, size: u32) -> Result<Opened, PnmError> {
    let hint = format!("{size}");
    let f = open(path, Kind::Ppm, &hint)?;
    let h = f.header;
    for (field, got) in [("width", h.width), ("height", h.height)] {
        if got != size {
            return Err(format_err(
                field,
                format!("expected {size} (one pixel per grid cell), got {got}"),
            ));
        }
    }
    if h.maxval != 255 {
        return Err(format_err(
            "maxval",
            format!("expected 255 (8-bit RGB), got {}", h.maxval),
        ));
    }
    check_length(&h, f.file_len)?;
    Ok(f)
}

/// Read an 8-bit RGB PPM of any size (at least 1 × 1, maxval 255), for `import --color`:
/// returns its width, height and pixels, row-major. The data length is checked against the
/// file's before the pixels are allocated. `progress` receives the bytes read so far.
pub fn read_ppm_any(
    path: &Path,
    progress: &mut dyn FnMut(u64),
) -> Result<(u32, u32, Vec<[u8; 3]>), PnmError> {
    let mut f = open(path, Kind::Ppm, "a size ≥ 1")?;
    let h = f.header;
    for (field, got) in [("width", h.width), ("height", h.height)] {
        if got == 0 {
            return Err(format_err(field, "expected a size ≥ 1, got 0"));
        }
    }
    if h.maxval != 255 {
        return Err(format_err(
            "maxval",
            format!(
                "expected 255 (8 bits a channel), got {}{}",
                h.maxval,
                if h.maxval > 255 {
                    " (16-bit colour: convert it to 8 bits)"
                } else {
                    ""
                }
            ),
        ));
    }
    check_length(&h, f.file_len)?;
    let count = usize::try_from(u64::from(h.width) * u64::from(h.height))
        .map_err(|_| format_err("width", "expected a smaller image"))?;
    let rgb = read_pixels(&mut f, count, progress)?;
    Ok((h.width, h.height, rgb))
}

/// Write a heightfield as a 16-bit binary PGM (maxval 65535, big-endian).
pub fn write_pgm(path: &Path, heights: &Heightfield) -> io::Result<()> {
    write_pgm_with(path, heights, &mut |_, _| {})
}

/// [`write_pgm`], reporting `(samples written, samples)` every few MB.
pub fn write_pgm_with(
    path: &Path,
    heights: &Heightfield,
    progress: &mut dyn FnMut(u64, u64),
) -> io::Result<()> {
    let mut w = BufWriter::with_capacity(CHUNK, File::create(path)?);
    write!(w, "P5\n{} {}\n65535\n", heights.side(), heights.side())?;
    let total = heights.samples().len() as u64;
    let mut done = 0;
    for chunk in heights.samples().chunks(CHUNK / 2) {
        let bytes: Vec<u8> = chunk.iter().flat_map(|s| s.to_be_bytes()).collect();
        w.write_all(&bytes)?;
        done += chunk.len() as u64;
        if done % (PROGRESS_STEP / 2) < chunk.len() as u64 {
            progress(done, total);
        }
    }
    let file = w.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()?;
    progress(total, total);
    Ok(())
}

/// Write an 8-bit RGB binary PPM (maxval 255). `rgb` holds `width × height` pixels, row-major.
pub fn write_ppm(path: &Path, width: u32, height: u32, rgb: &[[u8; 3]]) -> io::Result<()> {
    write_ppm_with(path, width, height, rgb, &mut |_, _| {})
}

/// [`write_ppm`], reporting `(bytes written, bytes)` every few MB.
pub fn write_ppm_with(
    path: &Path,
    width: u32,
    height: u32,
    rgb: &[[u8; 3]],
    progress: &mut dyn FnMut(u64, u64),
) -> io::Result<()> {
    if rgb.len() as u64 != u64::from(width) * u64::from(height) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "{} pixels for a {width} × {height} image: expected {}",
                rgb.len(),
                u64::from(width) * u64::from(height)
            ),
        ));
    }
    let mut w = BufWriter::with_capacity(CHUNK, File::create(path)?);
    write!(w, "P6\n{width} {height}\n255\n")?;
    let bytes = rgb.as_flattened();
    let total = bytes.len() as u64;
    let mut done = 0;
    for chunk in bytes.chunks(PROGRESS_STEP as usize) {
        w.write_all(chunk)?;
        done += chunk.len() as u64;
        progress(done, total);
    }
    let file = w.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()?;
    progress(total, total);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(bytes: &[u8], kind: Kind) -> Result<Header, PnmError> {
        let mut r = Counting {
            inner: bytes,
            consumed: 0,
        };
        read_header(&mut r, kind, "a size")
    }

    #[test]
    fn header_tokens() {
        let h = header(b"P5 # c\n#d\n 3\t3\r\n# x\n65535\n\x00", Kind::Pgm).unwrap();
        assert_eq!((h.width, h.height, h.maxval), (3, 3, 65535));
        assert_eq!(h.data_offset, 26);
        let h = header(b"P5\n5 5\n255 ", Kind::Pgm).unwrap();
        assert_eq!(h.bytes_per_sample(), 1);
        assert_eq!(h.data_len(), 25);
        let h = header(b"P6\n4 4\n255\n", Kind::Ppm).unwrap();
        assert_eq!(h.data_len(), 48);
    }

    #[test]
    fn header_errors() {
        for (bytes, want) in [
            (&b"P2\n3 3\n255\n"[..], "magic: expected \"P5\""),
            (b"P5", "width: expected a size, got end of file"),
            (b"P5x", "magic: expected whitespace after magic, got 'x'"),
            (
                b"P5\n-3 3\n255\n",
                "width: expected a size (a decimal number), got '-'",
            ),
            (
                b"P5\n3 3\n255",
                "maxval: expected a single whitespace byte after maxval, got end of file",
            ),
            (
                b"P5\n3 3\n255x",
                "maxval: expected a single whitespace byte",
            ),
            (b"P5\n3 3\n0\n", "maxval: expected 1 ..= 65535, got 0"),
            (
                b"P5\n3 3\n65536\n",
                "maxval: expected 1 ..= 65535, got 65536",
            ),
            (
                b"P5\n1234567890 3\n1\n",
                "width: expected a size, got a number of more",
            ),
        ] {
            let err = header(bytes, Kind::Pgm).unwrap_err().to_string();
            assert!(err.contains(want), "{bytes:?}: {err}");
        }
    }
}
