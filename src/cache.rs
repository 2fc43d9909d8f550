//! The content-addressed stage cache.
//!
//! Layout under the cache directory:
//!
//! ```text
//! lock                      shared by runs, exclusive for gc/verify (OFD lock)
//! objects/ab/cdef...        one file per distinct content, named by its blake3, read-only
//! entries/<key>.json        manifests: a complete entry exists iff its manifest does
//! locks/<key>.lock          per-key OFD lock held while a stage computes
//! tmp/<pid>-<n>-<key>/      staging directories of running stages (full key)
//! index/<pipeline>.json     per stage: the last key and preimage (for `status` reasons)
//! runs/<ms>-<pipeline>.json run reports
//! hints.json                (path, size, mtime, inode) -> blake3, to skip rehashing
//! ```
//!
//! Invariants:
//! - An entry is complete iff `entries/<key>.json` exists; it is written last,
//!   to a temporary name, fsynced and renamed, after every object it names was
//!   fsynced and renamed into place. A killed run leaves at most a staging
//!   directory and orphan objects, which `gc` removes.
//! - Objects are immutable and read-only; they are hard-linked (never copied
//!   unless linking fails) into stage inputs and `out/`.
//! - A cache hit does not rehash objects: it checks each object's size and its
//!   (size, mtime, inode) hint; an object without a matching hint is rehashed,
//!   and one whose hash no longer matches makes the entry a miss (reported,
//!   recomputed, and the object rewritten). `verify` rehashes everything.
//! - Hints are only recorded for files whose mtime is at least two seconds in
//!   the past, so a file rewritten within the same timestamp tick as it was
//!   hashed is never trusted (the "racy clean" problem of git).
//! - Locks are open-file-description record locks (`fcntl` `F_OFD_SETLK`/
//!   `F_OFD_SETLKW` over the whole file), not `flock`: on NFS (v3 through
//!   NLM, v4 natively), Lustre, GPFS and BeeGFS, record locks are the ones
//!   the file system arbitrates between machines, while `flock` may only be
//!   local to one client or be mapped onto them behind fure's back. Unlike
//!   classic POSIX record locks they belong to the open file description,
//!   not the process, so two threads of one process (two opens) exclude each
//!   other and closing an unrelated descriptor of the same file releases
//!   nothing. The kernel (or the lock manager, for a dead client) releases
//!   them when a process dies, so a lock left by a killed run is recovered
//!   by the next one; a per-key lock makes two runs (on any machines sharing
//!   the cache) that need the same stage compute it once, and a run never
//!   waits while holding a key lock, so there is no deadlock.
//! - A staging directory is named after its full key and is only used under
//!   that key's lock, so a run removes a leftover one exactly when it can
//!   take the key's lock: whatever machine created it, nobody is using it
//!   (process ids say nothing across the machines of a cluster).
//! - Nothing read from the cache is trusted as a path: a manifest is used only
//!   after [`validate_manifest`] (hex digests of the right length, plain file
//!   names, relative directory paths without `.`/`..`, its key and seal
//!   recomputed), and no symbolic link under the cache is ever followed
//!   (`O_NOFOLLOW` opens, `lstat`, shard directories checked once per run).
//!   `verify` reports and removes every violation.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::{self, File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::unix::fs::{MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::key::{self, FileRecord, Links};

/// Version of the cache layout and manifest format (2: manifests are sealed).
pub const CACHE_SCHEMA: u32 = 2;

#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("cache {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cache {path}: {message}")]
    Format { path: PathBuf, message: String },
    /// Something fure does not store or follow: a symbolic link, a FIFO, ...
    #[error("{path}: {message}")]
    Refused { path: PathBuf, message: String },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Whole-file open-file-description record locks (`F_OFD_*` of `fcntl`).
///
/// Record locks are the locks shared file systems (NFS through NLM or v4,
/// Lustre, GPFS, BeeGFS) arbitrate between machines; the OFD flavour is
/// owned by the open file description, so threads and separate opens of one
/// process exclude each other like separate processes do, and the lock goes
/// away when the description is closed or the process dies.
pub mod ofd {
    use std::fs::File;
    use std::os::unix::io::AsRawFd;

    fn request(exclusive: bool) -> libc::flock {
        // SAFETY: flock is plain data; all-zero is a valid value.
        let mut fl: libc::flock = unsafe { std::mem::zeroed() };
        fl.l_type = if exclusive {
            libc::F_WRLCK as libc::c_short
        } else {
            libc::F_RDLCK as libc::c_short
        };
        fl.l_whence = libc::SEEK_SET as libc::c_short;
        fl.l_start = 0;
        fl.l_len = 0; // to the end of the file, however long it grows
        fl.l_pid = 0; // required for OFD locks
        fl
    }

    /// Takes the lock without waiting: Ok(false) when another description holds
    /// a conflicting one.
    pub fn try_lock(f: &File, exclusive: bool) -> std::io::Result<bool> {
        let fl = request(exclusive);
        // SAFETY: a valid descriptor and a valid flock struct.
        let r = unsafe { libc::fcntl(f.as_raw_fd(), libc::F_OFD_SETLK, &fl) };
        if r == 0 {
            return Ok(true);
        }
        let e = std::io::Error::last_os_error();
        match e.raw_os_error() {
            Some(libc::EAGAIN) | Some(libc::EACCES) => Ok(false),
            _ => Err(e),
        }
    }

    /// Takes the lock, waiting as long as needed.
    pub fn lock(f: &File, exclusive: bool) -> std::io::Result<()> {
        let fl = request(exclusive);
        loop {
            // SAFETY: a valid descriptor and a valid flock struct.
            let r = unsafe { libc::fcntl(f.as_raw_fd(), libc::F_OFD_SETLKW, &fl) };
            if r == 0 {
                return Ok(());
            }
            let e = std::io::Error::last_os_error();
            if e.raw_os_error() != Some(libc::EINTR) {
                return Err(e);
            }
        }
    }

    /// Whether another description holds a lock that conflicts with taking
    /// this one (`F_OFD_GETLK`); the lock itself is not taken.
    pub fn conflicts(f: &File, exclusive: bool) -> std::io::Result<bool> {
        let mut fl = request(exclusive);
        // SAFETY: a valid descriptor and a valid flock struct.
        let r = unsafe { libc::fcntl(f.as_raw_fd(), libc::F_OFD_GETLK, &mut fl) };
        if r != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(fl.l_type != libc::F_UNLCK as libc::c_short)
    }
}

/// This machine's name, for lock holder lines (empty when unknown).
pub fn host_name() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length; gethostname NUL-terminates
    // when the name fits.
    let r = unsafe { libc::gethostname(buf.as_mut_ptr() as *mut libc::c_char, buf.len()) };
    if r != 0 {
        return String::new();
    }
    let n = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..n]).into_owned()
}

/// The line a key lock's holder writes into the lock file: `pid N on HOST`,
/// and the Slurm job when it runs in one.
fn holder_line() -> String {
    let mut s = format!("pid {}", std::process::id());
    let host = host_name();
    if !host.is_empty() {
        s.push_str(&format!(" on {host}"));
    }
    if let Ok(job) = std::env::var("SLURM_JOB_ID") {
        if !job.is_empty() && job.bytes().all(|b| b.is_ascii_digit()) {
            s.push_str(&format!(" (slurm job {job})"));
        }
    }
    s
}

/// One output of a cached stage.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct OutputRecord {
    /// File or directory name in the stage's output directory.
    pub file_name: String,
    pub dir: bool,
    /// File: blake3 of the bytes; directory: [`key::dir_hash`] of `files`.
    pub blake3: String,
    pub bytes: u64,
    /// Directory outputs: one record per file.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<FileRecord>,
}

impl OutputRecord {
    /// (object hash, bytes, path relative to the output) for every stored file.
    pub fn objects(&self) -> Vec<(&str, u64, String)> {
        if self.dir {
            self.files
                .iter()
                .map(|f| {
                    (
                        f.blake3.as_str(),
                        f.bytes,
                        format!("{}/{}", self.file_name, f.path),
                    )
                })
                .collect()
        } else {
            vec![(self.blake3.as_str(), self.bytes, self.file_name.clone())]
        }
    }
}

/// A cache entry's manifest.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub schema: u32,
    pub key: String,
    pub kind: String,
    /// Pipeline and stage that created the entry (informative only).
    pub pipeline: String,
    pub stage: String,
    pub preimage: key::Preimage,
    pub outputs: BTreeMap<String, OutputRecord>,
    pub seconds: f64,
    pub peak_rss_bytes: u64,
    /// Threads of the stage's pool when it ran (0: unknown, an entry from
    /// before this was recorded); `seconds` depend on it. Informative only,
    /// outside the seal.
    #[serde(default)]
    pub threads: u32,
    /// Cores other work used on average while the stage ran
    /// ([`crate::load`]; None: not measured). With `threads` it tells whether
    /// `seconds` were the stage's own. Informative only, outside the seal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub other_load: Option<f32>,
    pub fure_version: String,
    pub created_unix: u64,
    /// The stage's notes (what it chose, which device rendered), in order;
    /// informative only, outside the seal.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// blake3 over the key and the outputs ([`Manifest::compute_seal`]):
    /// an edited or damaged manifest naming other (valid) objects is
    /// detected. It is a checksum, not a signature: the cache's writers are
    /// trusted not to forge it, its paths are never trusted.
    #[serde(default)]
    pub seal: String,
}

impl Manifest {
    pub fn total_bytes(&self) -> u64 {
        self.outputs.values().map(|o| o.bytes).sum()
    }
    /// The seal this manifest should carry.
    pub fn compute_seal(&self) -> String {
        let mut h = blake3::Hasher::new();
        h.update(b"fure-manifest-v2\0");
        h.update(self.key.as_bytes());
        h.update(b"\0");
        h.update(&serde_json::to_vec(&self.outputs).unwrap_or_default());
        h.finalize().to_hex().to_string()
    }
    /// Sets the seal (the last step before writing).
    pub fn seal(mut self) -> Self {
        self.seal = self.compute_seal();
        self
    }
}

/// A blake3 digest as fure writes it: 64 lowercase hex digits.
pub fn is_digest(s: &str) -> bool {
    s.len() == 64 && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// A plain file name: not empty, not `.` or `..`, no `/` or NUL.
pub fn is_plain_name(s: &str) -> bool {
    !s.is_empty() && s != "." && s != ".." && !s.contains('/') && !s.contains('\0')
}

/// A relative path of plain names separated by single `/`.
pub fn is_relative_path(s: &str) -> bool {
    !s.is_empty() && s.split('/').all(is_plain_name)
}

/// Checks everything of a manifest that a run would use as a path or a
/// hash; Err says what is wrong. `key` is the name it was found under.
pub fn validate_manifest(m: &Manifest, key: &str) -> Result<(), String> {
    if m.schema != CACHE_SCHEMA {
        return Err(format!(
            "manifest schema {} (this fure writes {CACHE_SCHEMA})",
            m.schema
        ));
    }
    if !is_digest(key) || m.key != key {
        return Err(format!("manifest names key `{}`", m.key));
    }
    if m.preimage.key() != key {
        return Err("the preimage does not hash to the key".into());
    }
    let mut names = BTreeSet::new();
    for (port, o) in &m.outputs {
        let bad = |what: String| Err(format!("output `{port}`: {what}"));
        if !is_plain_name(&o.file_name) {
            return bad(format!("file name {:?} is not a plain name", o.file_name));
        }
        if !names.insert(o.file_name.as_str()) {
            return bad(format!("file name {:?} used twice", o.file_name));
        }
        if !is_digest(&o.blake3) {
            return bad(format!("hash {:?} is not a blake3 digest", o.blake3));
        }
        if !o.dir {
            if !o.files.is_empty() {
                return bad("a file with a file list".into());
            }
            continue;
        }
        let mut prev: Option<&str> = None;
        let mut total = 0u64;
        let paths: BTreeSet<&str> = o.files.iter().map(|f| f.path.as_str()).collect();
        for f in &o.files {
            if !is_relative_path(&f.path) {
                return bad(format!("path {:?} is not a relative path", f.path));
            }
            if !is_digest(&f.blake3) {
                return bad(format!(
                    "hash {:?} of {:?} is not a blake3 digest",
                    f.blake3, f.path
                ));
            }
            // Sorted and unique, and no file is also a directory.
            if prev.is_some_and(|p| p >= f.path.as_str()) {
                return bad(format!("path {:?} is out of order or repeated", f.path));
            }
            let clash = f
                .path
                .match_indices('/')
                .find(|(i, _)| paths.contains(&f.path[..*i]));
            if let Some((i, _)) = clash {
                return bad(format!(
                    "{:?} is a file and the directory of {:?}",
                    &f.path[..i],
                    f.path
                ));
            }
            prev = Some(&f.path);
            total = total.saturating_add(f.bytes);
        }
        if key::dir_hash(&o.files) != o.blake3 || total != o.bytes {
            return bad("the file list does not match the directory hash".into());
        }
    }
    if m.seal != m.compute_seal() {
        return Err("the seal does not match the outputs (edited or damaged manifest)".into());
    }
    Ok(())
}

/// Reads a file under the cache without following a symbolic link.
pub fn read_nofollow(path: &Path) -> std::io::Result<Vec<u8>> {
    let mut f = key::open_regular(path, Links::Refuse)?;
    let mut b = Vec::new();
    f.read_to_end(&mut b)?;
    Ok(b)
}

/// What `status` remembers of a stage's last resolution.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct IndexEntry {
    pub key: String,
    pub kind: String,
    pub version: u32,
    pub params: BTreeMap<String, fure_stage_api::Value>,
    /// port -> (source as written, content hash)
    pub inputs: BTreeMap<String, (String, String)>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
struct Hint {
    size: u64,
    mtime_ns: i64,
    ino: u64,
    hash: [u8; 32],
}

fn hint_of(md: &fs::Metadata, hash: &str) -> Option<Hint> {
    let h = blake3::Hash::from_hex(hash).ok()?;
    Some(Hint {
        size: md.len(),
        mtime_ns: md.mtime() * 1_000_000_000 + md.mtime_nsec(),
        ino: md.ino(),
        hash: *h.as_bytes(),
    })
}

fn hint_matches(h: &Hint, md: &fs::Metadata) -> bool {
    h.size == md.len()
        && h.ino == md.ino()
        && h.mtime_ns == md.mtime() * 1_000_000_000 + md.mtime_nsec()
}

/// Whether a file's mtime is old enough to trust a hint for it.
fn settled(md: &fs::Metadata) -> bool {
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs() as i64;
    md.mtime() + 2 <= now
}

#[derive(Default)]
struct Hints {
    map: BTreeMap<String, Hint>,
    dirty: bool,
}

/// How a cache is opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Runs, status: many at once.
    Shared,
    /// gc, verify: alone.
    Exclusive,
}

/// An open cache directory.
pub struct Cache {
    root: PathBuf,
    hints: Mutex<Hints>,
    /// None: a read-only cache without a lock file (hits only).
    _lock: Option<File>,
    counter: AtomicU64,
    /// Shard directories `objects/ab` found to be real directories (checked
    /// once per process, so a hit costs no extra `lstat`).
    shards: Vec<std::sync::atomic::AtomicBool>,
    /// Keys this process is computing: a stage of this run with the same key
    /// as another waits here, before the key's lock file (whose holder line
    /// may not be written yet, or be a previous run's).
    busy: Busy,
}

/// A held per-key lock (released on drop; the file lock first).
pub struct KeyLock {
    _file: File,
    _claim: KeyClaim,
}

/// The keys held by this process's threads, and their release signal.
type Busy = Arc<(Mutex<BTreeSet<String>>, Condvar)>;

/// A key claimed by one thread of this process (see `Cache::busy`),
/// released on drop.
pub struct KeyClaim {
    busy: Busy,
    key: String,
}

impl KeyClaim {
    /// Claims `key`, first waiting (after calling `waiting`) while another
    /// thread of this process holds it.
    fn acquire(busy: &Busy, key: &str, waiting: impl FnOnce()) -> KeyClaim {
        let (set, freed) = &**busy;
        let mut held = set.lock().unwrap_or_else(|e| e.into_inner());
        if held.contains(key) {
            drop(held);
            waiting();
            held = set.lock().unwrap_or_else(|e| e.into_inner());
            while held.contains(key) {
                held = freed.wait(held).unwrap_or_else(|e| e.into_inner());
            }
        }
        held.insert(key.to_string());
        KeyClaim {
            busy: busy.clone(),
            key: key.to_string(),
        }
    }
}

impl Drop for KeyClaim {
    fn drop(&mut self) {
        let (set, freed) = &*self.busy;
        set.lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.key);
        freed.notify_all();
    }
}

/// A staging directory, removed on drop.
pub struct Staging {
    pub path: PathBuf,
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = remove_tree(&self.path);
    }
}

/// Removes a tree even where files or directories are read-only.
pub fn remove_tree(path: &Path) -> std::io::Result<()> {
    match fs::remove_dir_all(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(_) => {
            // Make directories writable and retry.
            fn fix(p: &Path) {
                if let Ok(md) = fs::symlink_metadata(p) {
                    if md.is_dir() {
                        let _ = fs::set_permissions(p, fs::Permissions::from_mode(0o755));
                        if let Ok(rd) = fs::read_dir(p) {
                            for e in rd.flatten() {
                                fix(&e.path());
                            }
                        }
                    }
                }
            }
            fix(path);
            fs::remove_dir_all(path)
        }
    }
}

fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs()
}

/// Writes `bytes` to `path` atomically: temporary name, optional fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8], sync: bool) -> std::io::Result<()> {
    static N: AtomicU64 = AtomicU64::new(0);
    let tmp = path.with_extension(format!(
        "tmp-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let res = (|| {
        // create_new: a planted link at the temporary name is not followed.
        let _ = fs::remove_file(&tmp);
        let mut f = OpenOptions::new().write(true).create_new(true).open(&tmp)?;
        f.write_all(bytes)?;
        if sync {
            f.sync_all()?;
        }
        fs::rename(&tmp, path)?;
        if sync {
            if let Some(dir) = path.parent() {
                if let Ok(d) = File::open(dir) {
                    let _ = d.sync_all();
                }
            }
        }
        Ok(())
    })();
    if res.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    res
}

fn pid_alive(pid: u32) -> bool {
    Path::new(&format!("/proc/{pid}")).exists()
}

impl Cache {
    /// Opens (creating if needed) the cache at `root`.
    pub fn open(root: &Path, access: Access) -> Result<Cache, CacheError> {
        for sub in ["objects", "entries", "locks", "tmp", "index", "runs"] {
            let p = root.join(sub);
            match fs::symlink_metadata(&p) {
                Ok(md) if md.is_dir() => {}
                Ok(md) => {
                    return Err(CacheError::Refused {
                        message: format!(
                            "is {} where the cache keeps a directory; fure follows no links \
                             inside its cache (remove it)",
                            key::file_type_name(&md.file_type())
                        ),
                        path: p,
                    })
                }
                Err(_) => fs::create_dir_all(&p).map_err(io(&p))?,
            }
        }
        // Absolute, so command stages (which run elsewhere) see valid paths.
        let root = &root.canonicalize().map_err(io(root))?;
        let lock_path = root.join("lock");
        let flags = libc::O_NOFOLLOW | libc::O_CLOEXEC;
        let lock = match OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .custom_flags(flags)
            .open(&lock_path)
        {
            Ok(f) => Some(f),
            // A read-only cache still serves hits (a read lock needs only a read-only fd).
            Err(e) if access == Access::Shared && read_only_error(&e) => OpenOptions::new()
                .read(true)
                .custom_flags(flags)
                .open(&lock_path)
                .ok(),
            Err(e) => return Err(io(&lock_path)(e)),
        };
        let shards = (0..256)
            .map(|_| std::sync::atomic::AtomicBool::new(false))
            .collect();
        let Some(lock) = lock else {
            return Ok(Cache {
                root: root.to_path_buf(),
                hints: Mutex::new(Hints::default()),
                _lock: None,
                counter: AtomicU64::new(0),
                shards,
                busy: Default::default(),
            });
        };
        let exclusive = access == Access::Exclusive;
        if !ofd::try_lock(&lock, exclusive).map_err(io(&lock_path))? {
            eprintln!(
                "waiting for other fure processes using the cache {} ...",
                root.display()
            );
            ofd::lock(&lock, exclusive).map_err(io(&lock_path))?;
        }
        let hints_path = root.join("hints.json");
        let map = read_nofollow(&hints_path)
            .ok()
            .and_then(|b| serde_json::from_slice::<BTreeMap<String, Hint>>(&b).ok())
            .unwrap_or_default();
        Ok(Cache {
            root: root.to_path_buf(),
            hints: Mutex::new(Hints { map, dirty: false }),
            _lock: Some(lock),
            counter: AtomicU64::new(0),
            shards,
            busy: Default::default(),
        })
    }

    /// Checks that the shard directory of `hash` is not a link (or anything
    /// else but a directory); a missing shard is fine (the object is missing).
    fn check_shard(&self, hash: &str) -> Result<(), String> {
        let Some(i) = hash
            .get(..2)
            .and_then(|a| usize::from_str_radix(a, 16).ok())
        else {
            return Err(format!("{hash:?} is not a blake3 digest"));
        };
        if self.shards[i].load(Ordering::Relaxed) {
            return Ok(());
        }
        let p = self.root.join("objects").join(&hash[..2]);
        match fs::symlink_metadata(&p) {
            Ok(md) if md.is_dir() => {
                self.shards[i].store(true, Ordering::Relaxed);
                Ok(())
            }
            Ok(md) => Err(format!(
                "{} is {}, not a directory (run `fure verify`)",
                p.display(),
                key::file_type_name(&md.file_type())
            )),
            Err(_) => Ok(()),
        }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Bytes an unprivileged writer may still use on the cache's file system (`statvfs`'s
    /// available blocks), or `None` when the system does not say.
    pub fn free_bytes(&self) -> Option<u64> {
        use std::os::unix::ffi::OsStrExt;
        let path = std::ffi::CString::new(self.root.as_os_str().as_bytes()).ok()?;
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        // SAFETY: `path` is a NUL-terminated string and `st` a statvfs the call fills.
        let r = unsafe { libc::statvfs(path.as_ptr(), &mut st) };
        (r == 0).then(|| (st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
    }

    /// Saves the hint table if it changed.
    pub fn save_hints(&self) {
        let h = self.hints.lock().unwrap_or_else(|e| e.into_inner());
        if h.dirty {
            if let Ok(b) = serde_json::to_vec(&h.map) {
                let _ = write_atomic(&self.root.join("hints.json"), &b, false);
            }
        }
    }

    fn hint_get(&self, key: &str) -> Option<Hint> {
        self.hints
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .map
            .get(key)
            .copied()
    }

    fn hint_put(&self, key: String, md: &fs::Metadata, hash: &str) {
        if !settled(md) {
            return;
        }
        if let Some(h) = hint_of(md, hash) {
            let mut hs = self.hints.lock().unwrap_or_else(|e| e.into_inner());
            if hs.map.get(&key) != Some(&h) {
                hs.map.insert(key, h);
                hs.dirty = true;
            }
        }
    }

    /// blake3 of a file, using the hint table to avoid rereading unchanged files.
    pub fn hash_file_hinted(&self, path: &Path) -> std::io::Result<(String, u64)> {
        let md = fs::metadata(path)?;
        if !md.is_file() {
            return Err(key::not_regular(path, &md.file_type()));
        }
        let k = path.to_string_lossy().into_owned();
        if let Some(h) = self.hint_get(&k) {
            if hint_matches(&h, &md) {
                return Ok((
                    blake3::Hash::from_bytes(h.hash).to_hex().to_string(),
                    md.len(),
                ));
            }
        }
        let (hash, n) = key::hash_file(path)?;
        self.hint_put(k, &md, &hash);
        Ok((hash, n))
    }

    /// Content hash of an input file or directory (with hints); bytes; is_dir.
    pub fn hash_source(&self, path: &Path) -> std::io::Result<(String, u64, bool)> {
        if path.is_dir() {
            let mut files = Vec::new();
            let mut total = 0;
            for (rel, p) in key::list_dir(path)? {
                let (h, n) = self.hash_file_hinted(&p)?;
                total += n;
                files.push(FileRecord {
                    path: rel,
                    blake3: h,
                    bytes: n,
                });
            }
            Ok((key::dir_hash(&files), total, true))
        } else {
            let (h, n) = self.hash_file_hinted(path)?;
            Ok((h, n, false))
        }
    }

    /// The path of an object; `hash` must be a digest (manifests are
    /// validated before their hashes are used).
    pub fn object_path(&self, hash: &str) -> PathBuf {
        debug_assert!(is_digest(hash), "{hash:?}");
        let (a, b) = hash.split_at(2.min(hash.len()));
        self.root.join("objects").join(a).join(b)
    }

    /// Checks that an object exists with the right size and content (content
    /// by hint when possible). Err describes the problem.
    pub fn check_object(&self, hash: &str, bytes: u64) -> Result<(), String> {
        if !is_digest(hash) {
            return Err(format!("{hash:?} is not a blake3 digest"));
        }
        self.check_shard(hash)?;
        let p = self.object_path(hash);
        let md =
            fs::symlink_metadata(&p).map_err(|_| format!("object {} is missing", short(hash)))?;
        if !md.is_file() {
            return Err(format!(
                "object {} is {}",
                short(hash),
                key::file_type_name(&md.file_type())
            ));
        }
        if md.len() != bytes {
            return Err(format!(
                "object {} is corrupted (size {} instead of {bytes})",
                short(hash),
                md.len()
            ));
        }
        let k = p.to_string_lossy().into_owned();
        if let Some(h) = self.hint_get(&k) {
            if hint_matches(&h, &md)
                && h.hash
                    == blake3::Hash::from_hex(hash)
                        .map(|x| *x.as_bytes())
                        .unwrap_or_default()
            {
                return Ok(());
            }
        }
        match key::open_regular(&p, Links::Refuse).and_then(|mut f| key::hash_open(&mut f)) {
            Ok((h, _)) if h == hash => {
                self.hint_put(k, &md, hash);
                Ok(())
            }
            Ok(_) => Err(format!(
                "object {} is corrupted (hash mismatch)",
                short(hash)
            )),
            Err(e) => Err(format!("object {} is unreadable: {e}", short(hash))),
        }
    }

    /// Reads a valid manifest; `None` if absent, unreadable or invalid.
    pub fn lookup(&self, key: &str) -> Option<Manifest> {
        self.lookup_checked(key).ok().flatten()
    }

    /// Reads a manifest: Ok(None) if absent, Err(why) if it is there but
    /// unreadable or fails [`validate_manifest`] (the entry is damaged).
    pub fn lookup_checked(&self, key: &str) -> Result<Option<Manifest>, String> {
        if !is_digest(key) {
            return Err(format!("{key:?} is not a key"));
        }
        let p = self.root.join("entries").join(format!("{key}.json"));
        let b = match read_nofollow(&p) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("manifest unreadable: {e}")),
        };
        let m: Manifest =
            serde_json::from_slice(&b).map_err(|e| format!("manifest unreadable: {e}"))?;
        if m.schema != CACHE_SCHEMA {
            // An older fure's entry: a plain miss, rewritten by this run.
            return Ok(None);
        }
        validate_manifest(&m, key).map_err(|e| format!("invalid manifest: {e}"))?;
        Ok(Some(m))
    }

    /// Checks every object of an entry; Err names the first problem.
    pub fn check_entry(&self, m: &Manifest) -> Result<(), String> {
        for (port, o) in &m.outputs {
            for (h, n, _) in o.objects() {
                self.check_object(h, n)
                    .map_err(|e| format!("output `{port}`: {e}"))?;
            }
        }
        Ok(())
    }

    /// Moves a staged file into the object store; returns its hash and size.
    ///
    /// Nothing is followed: a symbolic link is refused, and a file with other
    /// hard links (its inode is shared with something outside the staging
    /// directory) is copied first, so the outside file is never made
    /// read-only nor turned into an object that can change under the cache.
    pub fn store_file(&self, staged: &Path) -> Result<(String, u64), CacheError> {
        let refused = |e: std::io::Error| {
            if e.kind() == std::io::ErrorKind::InvalidInput {
                CacheError::Refused {
                    path: staged.to_path_buf(),
                    message: format!(
                        "{e}; a stage's outputs must be regular files and directories"
                    ),
                }
            } else {
                io(staged)(e)
            }
        };
        let mut f = key::open_regular(staged, Links::Refuse).map_err(refused)?;
        let md = f.metadata().map_err(io(staged))?;
        if md.nlink() > 1 {
            let n = self.counter.fetch_add(1, Ordering::Relaxed);
            let copy = staged.with_file_name(format!(".fure-copy-{}-{n}", std::process::id()));
            let _ = fs::remove_file(&copy);
            let mut c = OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&copy)
                .map_err(io(&copy))?;
            std::io::copy(&mut f, &mut c).map_err(io(&copy))?;
            drop(c);
            // Unlink our name of the shared inode, then put the copy in its place.
            fs::remove_file(staged).map_err(io(staged))?;
            fs::rename(&copy, staged).map_err(io(staged))?;
            f = key::open_regular(staged, Links::Refuse).map_err(refused)?;
        }
        let (hash, n) = key::hash_open(&mut f).map_err(io(staged))?;
        self.check_shard(&hash)
            .map_err(|message| CacheError::Refused {
                path: self.root.join("objects"),
                message,
            })?;
        let dest = self.object_path(&hash);
        if fs::symlink_metadata(&dest).is_ok() && self.check_object(&hash, n).is_ok() {
            let _ = fs::remove_file(staged);
            return Ok((hash, n));
        }
        if let Some(parent) = dest.parent() {
            fs::create_dir_all(parent).map_err(io(parent))?;
        }
        f.sync_all().map_err(io(staged))?;
        // fchmod on our descriptor: never through a name that may have changed.
        f.set_permissions(fs::Permissions::from_mode(0o444))
            .map_err(io(staged))?;
        drop(f);
        // A corrupted object (or anything else) in the way is replaced by the rename.
        if fs::rename(staged, &dest).is_err() {
            // Cross-device staging (should not happen: tmp/ is inside the cache): copy.
            let tmp = dest.with_extension(format!("tmp-{}", std::process::id()));
            let _ = fs::remove_file(&tmp);
            let mut src = key::open_regular(staged, Links::Refuse).map_err(refused)?;
            src.rewind().map_err(io(staged))?;
            let mut t = OpenOptions::new()
                .write(true)
                .create_new(true)
                .mode(0o444)
                .open(&tmp)
                .map_err(io(&tmp))?;
            std::io::copy(&mut src, &mut t).map_err(io(&tmp))?;
            t.sync_all().map_err(io(&tmp))?;
            fs::rename(&tmp, &dest).map_err(io(&dest))?;
            let _ = fs::remove_file(staged);
        }
        Ok((hash, n))
    }

    /// Stores a staged output (file or directory) as objects. Links inside
    /// an output directory, or an output that is a link, are refused.
    pub fn store_output(
        &self,
        staged: &Path,
        file_name: &str,
        dir: bool,
    ) -> Result<OutputRecord, CacheError> {
        let md = fs::symlink_metadata(staged).map_err(io(staged))?;
        if md.is_dir() != dir || md.file_type().is_symlink() {
            return Err(CacheError::Refused {
                path: staged.to_path_buf(),
                message: format!(
                    "output `{file_name}` is {} but should be {}",
                    key::file_type_name(&md.file_type()),
                    if dir { "a directory" } else { "a regular file" }
                ),
            });
        }
        if dir {
            let list = key::list_tree(staged, Links::Refuse).map_err(|e| {
                if e.kind() == std::io::ErrorKind::InvalidInput {
                    CacheError::Refused {
                        path: staged.to_path_buf(),
                        message: format!(
                            "output `{file_name}`: {e}; a stage's outputs must be regular \
                             files and directories"
                        ),
                    }
                } else {
                    io(staged)(e)
                }
            })?;
            let mut files = Vec::with_capacity(list.len());
            let mut total = 0;
            for (rel, p) in list {
                let (h, n) = self.store_file(&p)?;
                total += n;
                files.push(FileRecord {
                    path: rel,
                    blake3: h,
                    bytes: n,
                });
            }
            Ok(OutputRecord {
                file_name: file_name.to_string(),
                dir: true,
                blake3: key::dir_hash(&files),
                bytes: total,
                files,
            })
        } else {
            let (h, n) = self.store_file(staged)?;
            Ok(OutputRecord {
                file_name: file_name.to_string(),
                dir: false,
                blake3: h,
                bytes: n,
                files: Vec::new(),
            })
        }
    }

    /// Writes a manifest (the entry becomes visible atomically).
    pub fn write_manifest(&self, m: &Manifest) -> Result<(), CacheError> {
        let p = self.root.join("entries").join(format!("{}.json", m.key));
        let b = serde_json::to_vec_pretty(m).map_err(|e| CacheError::Format {
            path: p.clone(),
            message: e.to_string(),
        })?;
        write_atomic(&p, &b, true).map_err(io(&p))
    }

    /// Opens (creating) a key's lock file: never through a link, and only a
    /// regular file.
    fn open_key_lock(&self, p: &Path) -> Result<File, CacheError> {
        // O_NOFOLLOW: a planted link must not make us truncate another file.
        let f = OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
            .open(p)
            .map_err(|e| {
                if e.raw_os_error() == Some(libc::ELOOP) {
                    CacheError::Refused {
                        path: p.to_path_buf(),
                        message: "is a symbolic link; fure follows no links inside its cache \
                                  (run `fure verify`)"
                            .into(),
                    }
                } else {
                    io(p)(e)
                }
            })?;
        let ft = f.metadata().map_err(io(p))?.file_type();
        if !ft.is_file() {
            return Err(CacheError::Refused {
                path: p.to_path_buf(),
                message: format!(
                    "is {}, not a lock file (run `fure verify`)",
                    key::file_type_name(&ft)
                ),
            });
        }
        Ok(f)
    }

    /// Takes the per-key lock, calling `waiting` before each wait: with
    /// `this run` while another thread of this process holds the key (two
    /// stages of one pipeline with one key), then with the holder's pid line
    /// if another process holds it.
    pub fn lock_key(&self, key: &str, waiting: &dyn Fn(&str)) -> Result<KeyLock, CacheError> {
        let claim = KeyClaim::acquire(&self.busy, key, || waiting("this run"));
        let p = self.root.join("locks").join(format!("{key}.lock"));
        let mut f = self.open_key_lock(&p)?;
        if !ofd::try_lock(&f, true).map_err(io(&p))? {
            let mut holder = String::new();
            let _ = (&f).read_to_string(&mut holder);
            let own = holder_line();
            waiting(match holder.trim() {
                h if h == own => "this run",
                // It has locked but not yet written its line.
                "" => "pid unknown",
                h => h,
            });
            ofd::lock(&f, true).map_err(io(&p))?;
        }
        let _ = f.set_len(0);
        let _ = writeln!(f, "{}", holder_line());
        Ok(KeyLock {
            _file: f,
            _claim: claim,
        })
    }

    /// Claims `key` among this process's threads only (no file lock): a
    /// driver that hands the computation to another machine holds the claim
    /// while the job runs, so two stages of its runs never submit one key
    /// twice, and lets the job take the file lock.
    pub fn claim_key(&self, key: &str, waiting: &dyn Fn()) -> KeyClaim {
        KeyClaim::acquire(&self.busy, key, waiting)
    }

    /// Waits until no other process (on any machine) computes `key`: takes
    /// its file lock and releases it at once. With the claim of
    /// [`Cache::claim_key`] held, a driver then finds the entry another run
    /// just finished instead of submitting a job that would wait for it.
    pub fn wait_key_free(&self, key: &str, waiting: &dyn Fn(&str)) -> Result<(), CacheError> {
        let p = self.root.join("locks").join(format!("{key}.lock"));
        let f = match self.open_key_lock(&p) {
            Ok(f) => f,
            Err(CacheError::Io { source, .. }) if read_only_error(&source) => return Ok(()),
            Err(e) => return Err(e),
        };
        if !ofd::try_lock(&f, true).map_err(io(&p))? {
            let mut holder = String::new();
            let _ = (&f).read_to_string(&mut holder);
            waiting(match holder.trim() {
                "" => "pid unknown",
                h => h,
            });
            ofd::lock(&f, true).map_err(io(&p))?;
        }
        Ok(())
    }

    /// Whether some open file description (of any process, or of this one
    /// through another open) holds `key`'s lock.
    pub fn key_locked(&self, key: &str) -> bool {
        let p = self.root.join("locks").join(format!("{key}.lock"));
        match self.open_key_lock(&p) {
            Ok(f) => ofd::conflicts(&f, true).unwrap_or(false),
            Err(_) => false,
        }
    }

    /// A fresh staging directory for one stage run.
    pub fn staging(&self, key: &str) -> Result<Staging, CacheError> {
        let n = self.counter.fetch_add(1, Ordering::Relaxed);
        let p = self
            .root
            .join("tmp")
            .join(format!("{}-{n}-{key}", std::process::id()));
        let _ = remove_tree(&p);
        fs::create_dir_all(&p).map_err(io(&p))?;
        Ok(Staging { path: p })
    }

    /// Removes staging directories nobody uses: a directory named after a
    /// full key goes when its key's lock can be taken (whatever machine made
    /// it: its maker held that lock while using it); an older name with a
    /// short key goes when its process is gone from this machine.
    pub fn clean_tmp(&self) -> usize {
        let mut n = 0;
        if let Ok(rd) = fs::read_dir(self.root.join("tmp")) {
            for e in rd.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                let full_key = name.rsplit('-').next().filter(|k| is_digest(k));
                let unused = match full_key {
                    Some(k) => {
                        let p = self.root.join("locks").join(format!("{k}.lock"));
                        // Keep the lock while removing, so nobody starts
                        // using a directory of that key meanwhile.
                        let guard = self
                            .open_key_lock(&p)
                            .ok()
                            .filter(|f| ofd::try_lock(f, true).unwrap_or(false));
                        if guard.is_some() {
                            let _ = remove_tree(&e.path());
                            n += 1;
                        }
                        continue;
                    }
                    None => {
                        let pid: Option<u32> = name.split('-').next().and_then(|s| s.parse().ok());
                        pid.map(|p| p != std::process::id() && !pid_alive(p))
                            .unwrap_or(true)
                    }
                };
                if unused {
                    let _ = remove_tree(&e.path());
                    n += 1;
                }
            }
        }
        n
    }

    fn index_path(&self, pipeline: &str) -> PathBuf {
        self.root.join("index").join(format!("{pipeline}.json"))
    }

    pub fn load_index(&self, pipeline: &str) -> BTreeMap<String, IndexEntry> {
        read_nofollow(&self.index_path(pipeline))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default()
    }

    pub fn save_index(&self, pipeline: &str, index: &BTreeMap<String, IndexEntry>) {
        if let Ok(b) = serde_json::to_vec_pretty(index) {
            let _ = write_atomic(&self.index_path(pipeline), &b, false);
        }
    }

    /// Keeps a run report; returns its path.
    pub fn save_run_report(&self, pipeline: &str, json: &[u8]) -> Option<PathBuf> {
        let ms = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default()
            .as_millis();
        let p = self
            .root
            .join("runs")
            .join(format!("{ms}-{pipeline}-{}.json", std::process::id()));
        write_atomic(&p, json, false).ok().map(|_| p)
    }

    /// Every valid manifest (key -> manifest, mtime), and what else is in
    /// `entries/`: (path, Some(why) to report, None for a temporary leftover).
    #[allow(clippy::type_complexity)]
    fn all_entries(
        &self,
    ) -> (
        BTreeMap<String, (Manifest, u64)>,
        Vec<(PathBuf, Option<String>)>,
    ) {
        let mut ok = BTreeMap::new();
        let mut bad = Vec::new();
        if let Ok(rd) = fs::read_dir(self.root.join("entries")) {
            for e in rd.flatten() {
                let p = e.path();
                let name = e.file_name().to_string_lossy().into_owned();
                let ft = e.file_type().ok();
                let key = name.strip_suffix(".json").filter(|k| is_digest(k));
                let Some(key) = key.filter(|_| ft.is_some_and(|t| t.is_file())) else {
                    let why = match ft {
                        Some(t) if t.is_file() && name.contains(".tmp-") => None,
                        Some(t) => Some(format!(
                            "entries/{name}: {} that is no manifest",
                            key::file_type_name(&t)
                        )),
                        None => Some(format!("entries/{name}: unreadable")),
                    };
                    bad.push((p, why));
                    continue;
                };
                let mtime = e.metadata().map(|m| m.mtime() as u64).unwrap_or(0);
                let parsed = read_nofollow(&p)
                    .map_err(|e| e.to_string())
                    .and_then(|b| serde_json::from_slice::<Manifest>(&b).map_err(|e| e.to_string()))
                    .and_then(|m| validate_manifest(&m, key).map(|()| m));
                match parsed {
                    Ok(m) => {
                        ok.insert(key.to_string(), (m, mtime));
                    }
                    Err(why) => bad.push((p, Some(format!("entry {key}: {why}")))),
                }
            }
        }
        (ok, bad)
    }

    /// Every object (hash, path, size), and whatever else is under
    /// `objects/` (path, description); nothing is followed.
    #[allow(clippy::type_complexity)]
    fn all_objects(&self) -> (Vec<(String, PathBuf, u64)>, Vec<(PathBuf, String)>) {
        let hex = |s: &str| s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'));
        let mut out = Vec::new();
        let mut strays = Vec::new();
        if let Ok(rd) = fs::read_dir(self.root.join("objects")) {
            for d in rd.flatten() {
                let a = d.file_name().to_string_lossy().into_owned();
                let ft = d.file_type().ok();
                if !(ft.is_some_and(|t| t.is_dir()) && a.len() == 2 && hex(&a)) {
                    let what = ft.map(|t| key::file_type_name(&t)).unwrap_or("unreadable");
                    strays.push((
                        d.path(),
                        format!("objects/{a}: {what} where a shard directory belongs"),
                    ));
                    continue;
                }
                if let Ok(rd2) = fs::read_dir(d.path()) {
                    for e in rd2.flatten() {
                        let b = e.file_name().to_string_lossy().into_owned();
                        let ft = e.file_type().ok();
                        if ft.is_some_and(|t| t.is_file()) && b.len() == 62 && hex(&b) {
                            let n = e.metadata().map(|m| m.len()).unwrap_or(0);
                            out.push((format!("{a}{b}"), e.path(), n));
                        } else {
                            let what = ft.map(|t| key::file_type_name(&t)).unwrap_or("unreadable");
                            strays.push((
                                e.path(),
                                format!("objects/{a}/{b}: {what} that is no object"),
                            ));
                        }
                    }
                }
            }
        }
        out.sort();
        (out, strays)
    }

    /// Removes a path found where it does not belong, without following it.
    fn remove_stray(p: &Path) {
        match fs::symlink_metadata(p) {
            Ok(md) if md.is_dir() => {
                let _ = remove_tree(p);
            }
            _ => {
                let _ = fs::remove_file(p);
            }
        }
    }

    /// Links, directories and other non-files in `locks/` and `index/`.
    fn strays_in(&self, sub: &str) -> Vec<(PathBuf, String)> {
        let mut out = Vec::new();
        if let Ok(rd) = fs::read_dir(self.root.join(sub)) {
            for e in rd.flatten() {
                match e.file_type() {
                    Ok(t) if t.is_file() => {}
                    t => out.push((
                        e.path(),
                        format!(
                            "{sub}/{}: {}",
                            e.file_name().to_string_lossy(),
                            t.map(|t| key::file_type_name(&t)).unwrap_or("unreadable")
                        ),
                    )),
                }
            }
        }
        out
    }

    /// Rehashes every object; drops corrupted objects and every entry that
    /// uses one, invalid manifests, and anything under the cache that fure
    /// does not write there (links, stray files), reporting each.
    pub fn verify(&self) -> VerifyReport {
        let mut rep = VerifyReport::default();
        let (objects, mut strays) = self.all_objects();
        strays.extend(self.strays_in("locks"));
        strays.extend(self.strays_in("index"));
        for (p, why) in strays {
            Self::remove_stray(&p);
            rep.violations.push(format!("{why} (removed)"));
        }
        let mut bad_objects = BTreeSet::new();
        for (name, path, _) in &objects {
            rep.objects_checked += 1;
            let good = matches!(
                key::open_regular(path, Links::Refuse).and_then(|mut f| key::hash_open(&mut f)),
                Ok((h, _)) if &h == name
            );
            if good {
                if let Ok(md) = fs::symlink_metadata(path) {
                    self.hint_put(path.to_string_lossy().into_owned(), &md, name);
                }
            } else {
                bad_objects.insert(name.clone());
                rep.corrupted_objects.push(name.clone());
                let _ = fs::remove_file(path);
            }
        }
        let present: BTreeSet<&String> = objects.iter().map(|(n, _, _)| n).collect();
        let (entries, bad) = self.all_entries();
        for (p, why) in bad {
            if let Some(why) = why {
                rep.broken_manifests.push(why.to_string());
            }
            Self::remove_stray(&p);
        }
        for (key, (m, _)) in &entries {
            rep.entries_checked += 1;
            let broken = m
                .outputs
                .values()
                .flat_map(|o| o.objects())
                .any(|(h, _, _)| bad_objects.contains(h) || !present.contains(&h.to_string()));
            if broken {
                rep.dropped_entries
                    .push(format!("{key} ({}/{})", m.pipeline, m.stage));
                let _ = fs::remove_file(self.root.join("entries").join(format!("{key}.json")));
            }
        }
        self.save_hints();
        rep
    }

    /// Garbage collection; see [`GcOptions`].
    pub fn gc(&self, opts: &GcOptions) -> GcReport {
        let mut rep = GcReport {
            tmp_removed: self.clean_tmp(),
            ..GcReport::default()
        };
        let (entries, bad) = self.all_entries();
        for (p, _) in bad {
            Self::remove_stray(&p);
        }
        // Entries the indexes point at were used by the latest run of some stage.
        let mut indexed = BTreeSet::new();
        if let Ok(rd) = fs::read_dir(self.root.join("index")) {
            for e in rd.flatten() {
                if let Some(ix) = read_nofollow(&e.path())
                    .ok()
                    .and_then(|b| serde_json::from_slice::<BTreeMap<String, IndexEntry>>(&b).ok())
                {
                    indexed.extend(ix.into_values().map(|i| i.key));
                }
            }
        }
        let mut live: BTreeMap<String, Manifest> = BTreeMap::new();
        let mut candidates: Vec<(bool, u64, String)> = Vec::new();
        for (key, (m, mtime)) in entries {
            let keep = opts.keep.as_ref().map(|k| k.contains(&key)).unwrap_or(true);
            if !keep {
                rep.entries_removed += 1;
                let _ = fs::remove_file(self.root.join("entries").join(format!("{key}.json")));
                continue;
            }
            let protected = opts
                .keep
                .as_ref()
                .map(|k| k.contains(&key))
                .unwrap_or(false);
            if !protected {
                candidates.push((indexed.contains(&key), mtime, key.clone()));
            }
            live.insert(key, m);
        }
        if let Some(max) = opts.max_size {
            // Evict unindexed entries first, oldest first, until objects fit.
            candidates.sort();
            let mut total = Self::referenced_size(&live);
            for (_, _, key) in candidates {
                if total <= max {
                    break;
                }
                live.remove(&key);
                let _ = fs::remove_file(self.root.join("entries").join(format!("{key}.json")));
                rep.entries_removed += 1;
                total = Self::referenced_size(&live);
            }
        }
        let referenced: BTreeSet<&str> = live
            .values()
            .flat_map(|m| m.outputs.values())
            .flat_map(|o| o.objects().into_iter().map(|(h, _, _)| h))
            .collect();
        let (objects, strays) = self.all_objects();
        // Links and strays are removed themselves, never what they point at.
        for (p, _) in strays {
            Self::remove_stray(&p);
        }
        for (name, path, n) in objects {
            if !referenced.contains(name.as_str()) {
                // Outputs are hard links to objects (`exec::link_output`): an
                // object still linked from an `out/` folder leaves the cache
                // but not the disk, and the report says so.
                let linked_outside = has_other_links(&path);
                let _ = fs::remove_file(&path);
                rep.objects_removed += 1;
                if linked_outside {
                    rep.bytes_linked_outside += n;
                } else {
                    rep.bytes_freed += n;
                }
            } else {
                rep.bytes_kept += n;
            }
        }
        // Under the exclusive lock no one holds key locks: drop the files
        // (remove_stray: a directory planted there goes too, links unfollowed).
        if let Ok(rd) = fs::read_dir(self.root.join("locks")) {
            for e in rd.flatten() {
                Self::remove_stray(&e.path());
            }
        }
        // Forget hints for files that are gone.
        {
            let mut h = self.hints.lock().unwrap_or_else(|e| e.into_inner());
            let before = h.map.len();
            h.map.retain(|path, _| Path::new(path).exists());
            if h.map.len() != before {
                h.dirty = true;
            }
        }
        self.save_hints();
        rep.entries_kept = live.len();
        rep
    }

    fn referenced_size(live: &BTreeMap<String, Manifest>) -> u64 {
        let mut seen = BTreeMap::new();
        for m in live.values() {
            for o in m.outputs.values() {
                for (h, n, _) in o.objects() {
                    seen.insert(h.to_string(), n);
                }
            }
        }
        seen.values().sum()
    }
}

/// What `gc` keeps.
#[derive(Debug, Default, Clone)]
pub struct GcOptions {
    /// When set, only these entries survive (`--keep PIPELINE`).
    pub keep: Option<BTreeSet<String>>,
    /// Evict (never kept) entries until referenced objects fit.
    pub max_size: Option<u64>,
}

#[derive(Debug, Default, Clone, Serialize)]
pub struct GcReport {
    pub entries_kept: usize,
    pub entries_removed: usize,
    pub objects_removed: usize,
    /// Bytes of removed objects that left the disk.
    pub bytes_freed: u64,
    /// Bytes of removed objects that stay on disk: other hard links to them
    /// remain (outputs under an `out/` folder, or a user's own link).
    pub bytes_linked_outside: u64,
    pub bytes_kept: u64,
    pub tmp_removed: usize,
}

/// Whether a file has hard links besides this path (never follows a link).
#[cfg(unix)]
fn has_other_links(path: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    fs::symlink_metadata(path).is_ok_and(|m| m.nlink() > 1)
}

#[cfg(not(unix))]
fn has_other_links(_path: &Path) -> bool {
    false
}

#[derive(Debug, Default, Clone, Serialize)]
pub struct VerifyReport {
    pub objects_checked: usize,
    pub entries_checked: usize,
    pub corrupted_objects: Vec<String>,
    pub dropped_entries: Vec<String>,
    /// Manifests that failed to parse or validate (removed), with the reason.
    pub broken_manifests: Vec<String>,
    /// Paths under the cache that fure never writes there: links, stray
    /// files or directories (removed, never followed).
    pub violations: Vec<String>,
}

impl VerifyReport {
    pub fn clean(&self) -> bool {
        self.corrupted_objects.is_empty()
            && self.dropped_entries.is_empty()
            && self.broken_manifests.is_empty()
            && self.violations.is_empty()
    }
}

/// Whether an error means the cache (or its file system) is read-only.
fn read_only_error(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EROFS) | Some(libc::EACCES) | Some(libc::EPERM)
    )
}

/// The first 12 hex digits of a hash, for messages.
pub fn short(hash: &str) -> &str {
    &hash[..hash.len().min(12)]
}

/// Parses sizes like `500M`, `10G`, `1.5GB`, `2048` (bytes; binary multiples).
pub fn parse_size(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let x: f64 = num
        .parse()
        .map_err(|_| format!("`{s}`: expected a size like 500M or 10G"))?;
    let mult: u64 = match unit.trim().to_ascii_uppercase().as_str() {
        "" | "B" => 1,
        "K" | "KB" | "KIB" => 1 << 10,
        "M" | "MB" | "MIB" => 1 << 20,
        "G" | "GB" | "GIB" => 1 << 30,
        "T" | "TB" | "TIB" => 1 << 40,
        u => return Err(format!("`{s}`: unknown unit `{u}` (expected K, M, G or T)")),
    };
    Ok((x * mult as f64) as u64)
}

/// Seconds since the epoch, for manifests.
pub fn created_now() -> u64 {
    now_unix()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cache_reads_its_disks_free_space() {
        let d = tempfile::tempdir().unwrap();
        let c = Cache::open(d.path(), Access::Shared).unwrap();
        let free = c
            .free_bytes()
            .expect("statvfs answers for a temporary directory");
        assert!(free > 0);
        // A cache that is not there has no disk to read.
        let gone = Cache {
            root: d.path().join("removed"),
            ..c
        };
        assert_eq!(gone.free_bytes(), None);
    }

    #[test]
    fn store_lookup_and_detect_corruption() {
        let d = tempfile::tempdir().unwrap();
        let c = Cache::open(d.path(), Access::Shared).unwrap();
        let st = c.staging("abcdef").unwrap();
        let f = st.path.join("out.txt");
        fs::write(&f, b"hello").unwrap();
        let rec = c.store_output(&f, "out.txt", false).unwrap();
        assert_eq!(rec.bytes, 5);
        assert!(c.check_object(&rec.blake3, 5).is_ok());
        // Corrupt the object in place (same size).
        let p = c.object_path(&rec.blake3);
        fs::set_permissions(&p, fs::Permissions::from_mode(0o644)).unwrap();
        fs::write(&p, b"jello").unwrap();
        let e = c.check_object(&rec.blake3, 5).unwrap_err();
        assert!(e.contains("hash mismatch"), "{e}");
        let v = c.verify();
        assert_eq!(v.corrupted_objects.len(), 1);
    }

    const KEY: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

    /// Key locks are OFD record locks: a second `Cache` of the same
    /// directory (another open file description, as another machine's run
    /// would have) waits for the first, and a plain `fcntl` probe of the
    /// lock file sees the lock (a `flock` would be invisible to it, and to
    /// a file system that arbitrates only record locks).
    #[test]
    fn key_locks_are_record_locks_between_opens() {
        let d = tempfile::tempdir().unwrap();
        let a = Cache::open(d.path(), Access::Shared).unwrap();
        let b = Cache::open(d.path(), Access::Shared).unwrap();
        assert!(!b.key_locked(KEY));
        let held = a.lock_key(KEY, &|_| panic!("free key")).unwrap();
        assert!(
            b.key_locked(KEY),
            "the lock is visible through another open"
        );
        let probe = File::open(d.path().join("locks").join(format!("{KEY}.lock"))).unwrap();
        assert!(
            ofd::conflicts(&probe, false).unwrap(),
            "F_OFD_GETLK sees it"
        );
        let text = fs::read_to_string(d.path().join("locks").join(format!("{KEY}.lock"))).unwrap();
        assert!(
            text.starts_with(&format!("pid {} on ", std::process::id())),
            "{text}"
        );

        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::scope(|s| {
            let b = &b;
            let waiter = s.spawn(move || {
                let holder = Mutex::new(String::new());
                let l = b.lock_key(KEY, &|h| *holder.lock().unwrap() = h.to_string());
                let _ = tx.send(());
                drop(l);
                holder.into_inner().unwrap()
            });
            std::thread::sleep(std::time::Duration::from_millis(200));
            assert!(rx.try_recv().is_err(), "the second open must wait");
            drop(held);
            // The holder line names this process: "this run".
            assert_eq!(waiter.join().unwrap(), "this run");
        });
        assert!(!a.key_locked(KEY));
    }

    /// The cache-wide lock: runs share it, gc/verify take it alone; also
    /// between two opens of one process.
    #[test]
    fn cache_lock_is_shared_or_exclusive() {
        let d = tempfile::tempdir().unwrap();
        let a = Cache::open(d.path(), Access::Shared).unwrap();
        let _b = Cache::open(d.path(), Access::Shared).unwrap();
        let f = OpenOptions::new()
            .read(true)
            .write(true)
            .open(d.path().join("lock"))
            .unwrap();
        assert!(ofd::conflicts(&f, true).unwrap(), "readers block a writer");
        assert!(!ofd::conflicts(&f, false).unwrap(), "readers share");
        drop(a);
        drop(_b);
        let _x = Cache::open(d.path(), Access::Exclusive).unwrap();
        assert!(ofd::conflicts(&f, false).unwrap(), "gc/verify are alone");
    }

    /// A staging directory is removed exactly when its key is not locked,
    /// whoever made it (its pid may be another machine's).
    #[test]
    fn clean_tmp_keeps_staging_dirs_of_locked_keys() {
        let d = tempfile::tempdir().unwrap();
        let a = Cache::open(d.path(), Access::Shared).unwrap();
        let other = "ffeeddccbbaa99887766554433221100ffeeddccbbaa99887766554433221100";
        // A live-looking pid (ours) of "another machine", key locked: kept.
        let _held = a.lock_key(KEY, &|_| {}).unwrap();
        let busy = a.staging(KEY).unwrap();
        // A pid that does not exist here, key free: removed.
        let stale = d.path().join("tmp").join(format!("1-0-{other}"));
        fs::create_dir_all(stale.join("out")).unwrap();
        let b = Cache::open(d.path(), Access::Shared).unwrap();
        assert_eq!(b.clean_tmp(), 1);
        assert!(busy.path.is_dir());
        assert!(!stale.exists());
    }

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("2048").unwrap(), 2048);
        assert_eq!(parse_size("1K").unwrap(), 1024);
        assert_eq!(parse_size("1.5G").unwrap(), 3 << 29);
        assert!(parse_size("12Q").is_err());
    }
}
