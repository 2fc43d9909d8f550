//! Stage keys and content hashes.
//!
//! A stage key is the blake3 hash of a canonical *preimage*: compact JSON of
//!
//! ```json
//! {"schema":1,"kind":"...","version":3,"params":{...},"inputs":{"port":"<blake3>"}}
//! ```
//!
//! with object keys sorted (BTreeMaps), and every parameter value tagged so
//! that types and floats are exact: `"i:5"`, `"f:3ff8000000000000"` (the f64
//! bit pattern), `"b:true"`, `"s:text"`; arrays and tables stay arrays and
//! objects of tagged values. Inputs enter by content hash only (file: blake3
//! of the bytes; directory: see [`hash_dir`]); paths, mtimes and host names
//! never do, so moving the project keeps every hit. `schema` is bumped when
//! this encoding or the cache layout changes. Which parameters enter at all is
//! the scheduler's choice (`exec::keyed_params`: all but a command's timeout and
//! an option declared `omit_default_from_key` while at its default).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Read;
use std::path::Path;

use fure_stage_api::{Params, Value};
use serde::{Deserialize, Serialize};

/// Version of the key preimage encoding.
pub const KEY_SCHEMA: u32 = 1;

/// The canonical form of a parameter value.
pub fn canonical_value(v: &Value) -> serde_json::Value {
    use serde_json::Value as J;
    match v {
        Value::Bool(b) => J::String(format!("b:{b}")),
        Value::Int(i) => J::String(format!("i:{i}")),
        Value::Float(f) => {
            // -0.0 and 0.0 behave the same in every stage we know; NaN never gets here.
            let f = if *f == 0.0 { 0.0f64 } else { *f };
            J::String(format!("f:{:016x}", f.to_bits()))
        }
        Value::Str(s) => J::String(format!("s:{s}")),
        Value::List(l) => J::Array(l.iter().map(canonical_value).collect()),
        Value::Table(t) => J::Object(
            t.iter()
                .map(|(k, v)| (k.clone(), canonical_value(v)))
                .collect(),
        ),
    }
}

/// Everything a stage's outputs may depend on.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Preimage {
    pub schema: u32,
    pub kind: String,
    pub version: u32,
    pub params: BTreeMap<String, serde_json::Value>,
    pub inputs: BTreeMap<String, String>,
}

impl Preimage {
    pub fn new(
        kind: &str,
        version: u32,
        params: &Params,
        inputs: BTreeMap<String, String>,
    ) -> Self {
        Preimage {
            schema: KEY_SCHEMA,
            kind: kind.to_string(),
            version,
            params: params
                .0
                .iter()
                .map(|(k, v)| (k.clone(), canonical_value(v)))
                .collect(),
            inputs,
        }
    }
    /// The canonical bytes that are hashed.
    pub fn bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }
    /// The key: blake3 of the canonical bytes, hex.
    pub fn key(&self) -> String {
        blake3::hash(&self.bytes()).to_hex().to_string()
    }
}

/// blake3 of a file's bytes and its length (a final symlink is followed;
/// anything but a regular file is refused).
pub fn hash_file(path: &Path) -> std::io::Result<(String, u64)> {
    hash_open(&mut open_regular(path, Links::Follow)?)
}

/// Opens a regular file for reading. Non-blocking, so a FIFO is refused
/// instead of hanging the open; with [`Links::Refuse`] a final symlink is
/// refused too (`O_NOFOLLOW`).
pub fn open_regular(path: &Path, links: Links) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut flags = libc::O_NONBLOCK | libc::O_CLOEXEC;
    if links == Links::Refuse {
        flags |= libc::O_NOFOLLOW;
    }
    let f = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(flags)
        .open(path)
        .map_err(|e| {
            if links == Links::Refuse && e.raw_os_error() == Some(libc::ELOOP) {
                std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!("{} is a symbolic link", path.display()),
                )
            } else {
                e
            }
        })?;
    let ft = f.metadata()?.file_type();
    if !ft.is_file() {
        return Err(not_regular(path, &ft));
    }
    Ok(f)
}

/// blake3 of an open file's bytes from its current position, and their length.
pub fn hash_open(f: &mut File) -> std::io::Result<(String, u64)> {
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut n = 0u64;
    loop {
        let k = match f.read(&mut buf) {
            Ok(k) => k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    Ok((h.finalize().to_hex().to_string(), n))
}

/// One file of a directory artifact.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq)]
pub struct FileRecord {
    /// Relative path with `/` separators.
    pub path: String,
    pub blake3: String,
    pub bytes: u64,
}

/// The hash of a directory: blake3 over `fure-dir-v1\0` then, for every file
/// in sorted relative-path order, `path \0 file-hash \n`. Empty directories
/// other than the root are not represented (only files are artifacts).
pub fn dir_hash(files: &[FileRecord]) -> String {
    let mut h = blake3::Hasher::new();
    h.update(b"fure-dir-v1\0");
    for f in files {
        h.update(f.path.as_bytes());
        h.update(b"\0");
        h.update(f.blake3.as_bytes());
        h.update(b"\n");
    }
    h.finalize().to_hex().to_string()
}

/// How [`list_tree`] treats symbolic links.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Links {
    /// Inputs: a user's data may be a tree of links; they are followed.
    Follow,
    /// Stage outputs: a link is refused, so storing never moves or reads
    /// anything outside the output directory.
    Refuse,
}

/// What a path is, for messages about non-regular files.
pub fn file_type_name(ft: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if ft.is_symlink() {
        "a symbolic link"
    } else if ft.is_dir() {
        "a directory"
    } else if ft.is_file() {
        "a regular file"
    } else if ft.is_fifo() {
        "a FIFO"
    } else if ft.is_socket() {
        "a socket"
    } else if ft.is_char_device() {
        "a character device"
    } else if ft.is_block_device() {
        "a block device"
    } else {
        "not a regular file"
    }
}

/// An `InvalidInput` error naming a path that is not a regular file or directory.
pub fn not_regular(path: &Path, ft: &std::fs::FileType) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!(
            "{} is {}, not a regular file or directory",
            path.display(),
            file_type_name(ft)
        ),
    )
}

/// Lists the files under `root` (following symlinks), sorted by relative
/// path. FIFOs, sockets and devices are refused (reading one would hang or
/// never end).
pub fn list_dir(root: &Path) -> std::io::Result<Vec<(String, std::path::PathBuf)>> {
    list_tree(root, Links::Follow)
}

/// Lists the regular files under `root`, sorted by relative path.
pub fn list_tree(root: &Path, links: Links) -> std::io::Result<Vec<(String, std::path::PathBuf)>> {
    fn walk(
        root: &Path,
        rel: &str,
        links: Links,
        out: &mut Vec<(String, std::path::PathBuf)>,
    ) -> std::io::Result<()> {
        let dir = if rel.is_empty() {
            root.to_path_buf()
        } else {
            root.join(rel)
        };
        for e in std::fs::read_dir(&dir)? {
            let e = e?;
            let name = e.file_name().to_string_lossy().into_owned();
            let r = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            let p = e.path();
            let ft = match links {
                Links::Follow => std::fs::metadata(&p)?.file_type(),
                // The entry's own type: never a stat through a link.
                Links::Refuse => e.file_type()?,
            };
            if ft.is_dir() {
                walk(root, &r, links, out)?;
            } else if ft.is_file() {
                out.push((r, p));
            } else {
                return Err(not_regular(&p, &ft));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(root, "", links, &mut out)?;
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// Hashes a directory tree: its file records and its Merkle hash.
pub fn hash_dir(root: &Path) -> std::io::Result<(String, u64, Vec<FileRecord>)> {
    let mut files = Vec::new();
    let mut total = 0;
    for (rel, p) in list_dir(root)? {
        let (h, n) = hash_file(&p)?;
        total += n;
        files.push(FileRecord {
            path: rel,
            blake3: h,
            bytes: n,
        });
    }
    Ok((dir_hash(&files), total, files))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(pairs: &[(&str, Value)]) -> Params {
        Params(
            pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.clone()))
                .collect(),
        )
    }

    #[test]
    fn key_depends_on_every_part_and_nothing_else() {
        let inputs = |h: &str| BTreeMap::from([("a".to_string(), h.to_string())]);
        let base = Preimage::new("k", 1, &params(&[("x", Value::Float(0.5))]), inputs("h1"));
        let same = Preimage::new("k", 1, &params(&[("x", Value::Float(0.5))]), inputs("h1"));
        assert_eq!(base.key(), same.key());
        let variants = [
            Preimage::new("k2", 1, &params(&[("x", Value::Float(0.5))]), inputs("h1")),
            Preimage::new("k", 2, &params(&[("x", Value::Float(0.5))]), inputs("h1")),
            Preimage::new(
                "k",
                1,
                &params(&[("x", Value::Float(0.5000000001))]),
                inputs("h1"),
            ),
            Preimage::new("k", 1, &params(&[("x", Value::Int(0))]), inputs("h1")),
            Preimage::new("k", 1, &params(&[("x", Value::Float(0.5))]), inputs("h2")),
        ];
        for v in &variants {
            assert_ne!(v.key(), base.key(), "{v:?}");
        }
        // A string that looks like a float is not the float.
        let s = Preimage::new(
            "k",
            1,
            &params(&[("x", Value::Str("0.5".into()))]),
            inputs("h1"),
        );
        assert_ne!(s.key(), base.key());
    }

    #[test]
    fn dir_hash_covers_names_and_contents() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("sub")).unwrap();
        std::fs::write(d.path().join("sub/a.txt"), b"A").unwrap();
        std::fs::write(d.path().join("b.txt"), b"B").unwrap();
        let (h1, n, files) = hash_dir(d.path()).unwrap();
        assert_eq!(n, 2);
        assert_eq!(files[0].path, "b.txt");
        assert_eq!(files[1].path, "sub/a.txt");
        std::fs::rename(d.path().join("b.txt"), d.path().join("c.txt")).unwrap();
        let (h2, _, _) = hash_dir(d.path()).unwrap();
        assert_ne!(h1, h2);
    }
}
