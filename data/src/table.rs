//! CSV tables through the `csv` crate with serde: every CSV file mavloc writes or reads
//! (ground truth, landmarks, border lines, trajectories, landings, residuals, traces, the
//! simulated vehicle's truth log) goes through here.
//!
//! A table's row type implements [`Row`], which names its header line. Files always start
//! with that header (also when there are no rows), rows end in `\n`, and fields are read
//! with surrounding spaces trimmed. Numbers keep the fixed decimals the files have always
//! had, through the serializers in [`fixed`], so existing files and their readers agree.

use std::fs;
use std::io::{self, Write};
use std::marker::PhantomData;
use std::path::Path;

use serde::de::DeserializeOwned;
use serde::Serialize;

/// A row of a CSV table.
pub trait Row: Serialize + DeserializeOwned {
    /// The header line, comma-separated, without the line end.
    const COLUMNS: &'static str;

    /// Number of columns in [`Row::COLUMNS`].
    fn column_count() -> usize {
        Self::COLUMNS.split(',').count()
    }
}

/// What went wrong reading a table; every message names the file (and line).
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    #[error("cannot read {origin}: {source}")]
    Io {
        origin: String,
        #[source]
        source: io::Error,
    },
    #[error("{origin}: the first line must {expected}")]
    Header { origin: String, expected: String },
    #[error("{origin} line {line}: {message}")]
    Line { origin: String, line: u64, message: String },
}

impl From<TableError> for String {
    fn from(e: TableError) -> String {
        e.to_string()
    }
}

/// How the first line of a table must look.
#[derive(Clone, Copy, Debug)]
pub enum Header<'a> {
    /// Exactly the row type's [`Row::COLUMNS`].
    Exact,
    /// Starting with these columns (older or wider variants of a file are accepted).
    StartsWith(&'a str),
}

/// How many fields a row must have.
#[derive(Clone, Copy, Debug)]
pub enum Columns {
    /// As many as the header names.
    Exact,
    /// At least this many; the row type reads the first ones, the rest are ignored.
    AtLeast(usize),
}

fn writer<W: Write>(w: W) -> csv::Writer<W> {
    csv::WriterBuilder::new().has_headers(false).terminator(csv::Terminator::Any(b'\n')).from_writer(w)
}

/// The table as text: the header line, then one line per row.
pub fn to_string<'a, T: Row + 'a>(rows: impl IntoIterator<Item = &'a T>) -> String {
    let mut w = writer(Vec::new());
    for r in rows {
        // Serialising to memory fails only on a row type that cannot be a CSV row, a bug.
        w.serialize(r).expect("a CSV row serialises");
    }
    let body = w.into_inner().expect("writing to memory cannot fail");
    let mut s = String::with_capacity(T::COLUMNS.len() + 1 + body.len());
    s.push_str(T::COLUMNS);
    s.push('\n');
    s.push_str(std::str::from_utf8(&body).expect("CSV of UTF-8 fields is UTF-8"));
    s
}

/// `text` without a leading UTF-8 byte-order mark: spreadsheet and Windows editors write
/// one, and it would otherwise be read as part of the first column's name or value.
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

/// Parses a table whose header is exactly `T::COLUMNS` and whose rows have as many fields.
pub fn parse<T: Row>(text: &str, origin: &str) -> Result<Vec<T>, TableError> {
    parse_with(text, origin, Header::Exact, Columns::Exact)
}

/// Parses a table, checking the header and the field count of each row as asked. Blank
/// lines are skipped; errors name `origin` and the line.
pub fn parse_with<T: Row>(
    text: &str,
    origin: &str,
    header: Header,
    columns: Columns,
) -> Result<Vec<T>, TableError> {
    let text = strip_bom(text);
    let (first, _) = text.split_once('\n').unwrap_or((text, ""));
    let first = first.trim();
    let ok = match header {
        Header::Exact => first == T::COLUMNS,
        Header::StartsWith(prefix) => first.starts_with(prefix),
    };
    if !ok {
        let expected = match header {
            Header::Exact => format!("be `{}`", T::COLUMNS),
            Header::StartsWith(prefix) => format!("start with `{prefix}`"),
        };
        return Err(TableError::Header { origin: origin.into(), expected });
    }
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(text.as_bytes());
    let want = T::column_count();
    let mut out = Vec::new();
    // csv counts records, not blank lines, and a record's offset may sit before the blank
    // lines it skipped: name the line from the first byte of the record's text instead.
    let bytes = text.as_bytes();
    let line_at = |p: Option<&csv::Position>| {
        p.map_or(0, |p| {
            let mut b = (p.byte() as usize).min(bytes.len());
            while b < bytes.len() && matches!(bytes[b], b'\n' | b'\r') {
                b += 1;
            }
            1 + bytes[..b].iter().filter(|&&c| c == b'\n').count() as u64
        })
    };
    for record in reader.records() {
        let record = record.map_err(|e| TableError::Line {
            origin: origin.into(),
            line: line_at(e.position()),
            message: e.to_string(),
        })?;
        // The line is counted only for an error: counting it for every row made reading a
        // table quadratic in its length (a 50 000-point ground truth took tens of seconds).
        let pos = record.position().cloned();
        let bad = |message: String| TableError::Line {
            origin: origin.into(),
            line: line_at(pos.as_ref()),
            message,
        };
        let record = match columns {
            Columns::Exact if record.len() != want => {
                return Err(bad(format!("expected {want} columns, got {}", record.len())));
            }
            Columns::AtLeast(n) if record.len() < n => {
                return Err(bad(format!("expected at least {n} columns, got {}", record.len())));
            }
            Columns::AtLeast(_) if record.len() > want => record.iter().take(want).collect(),
            _ => record,
        };
        let row: T = record.deserialize(None).map_err(|e| bad(deserialize_message(&e)))?;
        out.push(row);
    }
    Ok(out)
}

/// The rows of a table that parse, skipping the first line and any row that does not
/// (for optional extras whose absence or damage must not stop a run).
pub fn parse_lenient<T: Row>(text: &str) -> Vec<T> {
    let text = strip_bom(text);
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(text.as_bytes());
    let want = T::column_count();
    reader
        .records()
        .filter_map(|r| r.ok())
        .filter(|r| r.len() == want)
        .filter_map(|r| r.deserialize(None).ok())
        .collect()
}

/// csv's message without its own position prefix (the line is already named).
fn deserialize_message(e: &csv::Error) -> String {
    match e.kind() {
        csv::ErrorKind::Deserialize { err, .. } => match err.field() {
            Some(f) => format!("column {}: {}", f + 1, err.kind()),
            None => err.kind().to_string(),
        },
        _ => e.to_string(),
    }
}

/// Reads and parses a table file (see [`parse`]).
pub fn read<T: Row>(path: &Path) -> Result<Vec<T>, TableError> {
    let origin = path.display().to_string();
    let text =
        fs::read_to_string(path).map_err(|source| TableError::Io { origin: origin.clone(), source })?;
    parse(&text, &origin)
}

/// A table appended to row by row and flushed after each, so a crash loses at most the
/// row being written (live trajectories, traces, truth logs).
pub struct Appender<T> {
    w: csv::Writer<fs::File>,
    row: PhantomData<fn(&T)>,
}

impl<T: Row> Appender<T> {
    /// Opens `path` for appending; writes the header when the file is new or empty.
    pub fn append(path: &Path) -> io::Result<Appender<T>> {
        let fresh = fs::metadata(path).map(|m| m.len() == 0).unwrap_or(true);
        let file = fs::OpenOptions::new().create(true).append(true).open(path)?;
        Appender::start(file, fresh)
    }

    /// Creates (or truncates) `path` and writes the header.
    pub fn create(path: &Path) -> io::Result<Appender<T>> {
        Appender::start(fs::File::create(path)?, true)
    }

    fn start(mut file: fs::File, header: bool) -> io::Result<Appender<T>> {
        if header {
            writeln!(file, "{}", T::COLUMNS)?;
            file.flush()?;
        }
        Ok(Appender { w: writer(file), row: PhantomData })
    }

    /// Appends one row and flushes it to the file.
    pub fn push(&mut self, row: &T) -> io::Result<()> {
        self.w.serialize(row).map_err(io::Error::other)?;
        self.w.flush()
    }

    /// Appends rows and flushes them once.
    pub fn extend<'a>(&mut self, rows: impl IntoIterator<Item = &'a T>) -> io::Result<()>
    where
        T: 'a,
    {
        for r in rows {
            self.w.serialize(r).map_err(io::Error::other)?;
        }
        self.w.flush()
    }
}

/// Serializers that write numbers with fixed decimals (`{:.N}`), as mavloc's CSV files
/// always have; reading needs nothing special. Use with `#[serde(serialize_with = ...)]`.
pub mod fixed {
    use serde::{Deserialize, Deserializer, Serializer};

    macro_rules! decimals {
        ($($name:ident: $n:literal),*) => {$(
            #[doc = concat!("`{:.", stringify!($n), "}`")]
            pub fn $name<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
                s.collect_str(&format_args!("{:.*}", $n, v))
            }
        )*};
    }
    decimals!(dp2: 2, dp3: 3, dp4: 4, dp5: 5, dp6: 6, dp9: 9);

    macro_rules! optional {
        ($($name:ident: $inner:ident),*) => {$(
            #[doc = concat!("[`", stringify!($inner), "`], or an empty field for `None`.")]
            pub fn $name<S: Serializer>(v: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
                match v {
                    Some(v) => $inner(v, s),
                    None => s.serialize_str(""),
                }
            }
        )*};
    }
    optional!(opt_dp2: dp2, opt_dp4: dp4, opt_dp6: dp6);

    /// `{:.4}`, or an empty field for NaN (a value nobody knows: the ground-plane
    /// baseline's sigma). A spreadsheet or QGIS reads an empty field as missing, where
    /// "NaN" would make the whole column text.
    pub fn nan_empty_dp4<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_nan() {
            s.serialize_str("")
        } else {
            dp4(v, s)
        }
    }

    /// Reads what [`nan_empty_dp4`] writes: an empty field is NaN (so is "NaN", as files
    /// before session 41 have it).
    pub fn de_nan_empty<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        let text = String::deserialize(d)?;
        if text.trim().is_empty() {
            return Ok(f64::NAN);
        }
        text.trim().parse::<f64>().map_err(|_| serde::de::Error::custom(format!("`{text}` is not a number")))
    }

    /// Booleans as `1` and `0`.
    pub fn bool01<S: Serializer>(v: &bool, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u8(*v as u8)
    }

    /// Reads what [`bool01`] writes: any number, non-zero is true.
    pub fn de_bool01<'de, D: Deserializer<'de>>(d: D) -> Result<bool, D::Error> {
        Ok(f64::deserialize(d)? != 0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct T {
        id: u64,
        #[serde(serialize_with = "fixed::dp4")]
        x: f64,
        #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01")]
        ok: bool,
        #[serde(serialize_with = "fixed::opt_dp2")]
        m: Option<f64>,
        name: String,
    }

    impl Row for T {
        const COLUMNS: &'static str = "id,x,ok,m,name";
    }

    fn rows() -> Vec<T> {
        vec![
            T { id: 1, x: 0.5, ok: true, m: Some(1.0 / 3.0), name: "a".into() },
            T { id: 2, x: -1.0 / 3.0, ok: false, m: None, name: "b, c".into() },
        ]
    }

    #[test]
    fn writes_fixed_decimals_and_reads_them_back() {
        let text = to_string(&rows());
        assert_eq!(text, "id,x,ok,m,name\n1,0.5000,1,0.33,a\n2,-0.3333,0,,\"b, c\"\n");
        let back: Vec<T> = parse(&text, "t.csv").unwrap();
        assert_eq!(back[0].x, 0.5);
        assert_eq!(back[1].x, -0.3333);
        assert_eq!((back[0].ok, back[1].ok, back[1].m), (true, false, None));
        assert_eq!(back[1].name, "b, c");
        assert_eq!(to_string::<T>(&[]), "id,x,ok,m,name\n", "an empty table keeps its header");
    }

    /// A spreadsheet's save starts with a byte-order mark: read as the table it is, not
    /// refused for its header, and an error in it still names the right line.
    #[test]
    fn a_byte_order_mark_is_not_part_of_the_header() {
        let text = format!("\u{feff}{}", to_string(&rows()));
        let back: Vec<T> = parse(&text, "t.csv").unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(parse_lenient::<T>(&text).len(), 2);
        let e = parse::<T>("\u{feff}id,x,ok,m,name\n1,2,1,,a\n3,x,1,,a\n", "t.csv").unwrap_err().to_string();
        assert!(e.contains("line 3"), "{e}");
    }

    #[test]
    fn errors_name_the_file_and_line() {
        let e = parse::<T>("id,x\n", "t.csv").unwrap_err().to_string();
        assert!(e.starts_with("t.csv: the first line must be `id,x,ok,m,name`"), "{e}");
        let e = parse::<T>("id,x,ok,m,name\n1,2,1,,a\n\n3,x,1,,a\n", "t.csv").unwrap_err().to_string();
        assert!(e.starts_with("t.csv line 4: column 2"), "{e}");
        let e = parse::<T>("id,x,ok,m,name\n1,2,1\n", "t.csv").unwrap_err().to_string();
        assert_eq!(e, "t.csv line 2: expected 5 columns, got 3");
        let e = parse_with::<T>(
            "id,x,ok\n1, 2 ,1,,a,9\n",
            "t.csv",
            Header::StartsWith("id,x"),
            Columns::AtLeast(5),
        )
        .unwrap();
        assert_eq!(e[0].x, 2.0, "fields are trimmed, extra columns ignored");
        assert!(parse::<T>("id,x,ok,m,name\n1,NaN,0,,a\n", "t.csv").unwrap()[0].x.is_nan());
    }

    #[test]
    fn appender_writes_the_header_once_and_flushes_rows() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        let r = rows();
        Appender::<T>::append(&p).unwrap().push(&r[0]).unwrap();
        let mut a = Appender::<T>::append(&p).unwrap();
        a.push(&r[1]).unwrap();
        assert_eq!(fs::read_to_string(&p).unwrap(), to_string(&r));
        Appender::<T>::create(&p).unwrap().extend(&r[..1]).unwrap();
        assert_eq!(fs::read_to_string(&p).unwrap(), to_string(&r[..1]));
    }
}
