//! The content-addressed stage cache.
//!
//! Layout under the cache directory:
//!
//! ```text
//! lock                      shared by runs, exclusive for gc/verify (flock)
//! objects/ab/cdef...        one file per distinct content, named by its blake3, read-only
//! entries/<key>.json        manifests: a complete entry exists iff its manifest does
//! locks/<key>.lock          per-key flock held while a stage computes
//! tmp/<pid>-<n>-<key>/      staging directories of running stages
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
//! - Locks are `flock`s: the kernel releases them when a process dies, so a
//!   lock left by a killed run is recovered by the next one; a per-key lock
//!   makes two runs that need the same stage compute it once, and a run never
//!   waits while holding a key lock, so there is no deadlock.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::key::{self, FileRecord};

/// Version of the cache layout and manifest format.
pub const CACHE_SCHEMA: u32 = 1;

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
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
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
    pub fure_version: String,
    pub created_unix: u64,
}

impl Manifest {
    pub fn total_bytes(&self) -> u64 {
        self.outputs.values().map(|o| o.bytes).sum()
    }
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
    _lock: File,
    counter: AtomicU64,
}

/// A held per-key lock (released on drop).
pub struct KeyLock {
    _file: File,
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
        let mut f = File::create(&tmp)?;
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
            fs::create_dir_all(&p).map_err(io(&p))?;
        }
        // Absolute, so command stages (which run elsewhere) see valid paths.
        let root = &root.canonicalize().map_err(io(root))?;
        let lock_path = root.join("lock");
        let lock = OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&lock_path)
            .map_err(io(&lock_path))?;
        let got = match access {
            Access::Shared => lock.try_lock_shared(),
            Access::Exclusive => lock.try_lock(),
        };
        if got.is_err() {
            eprintln!(
                "waiting for other fure processes using the cache {} ...",
                root.display()
            );
            match access {
                Access::Shared => lock.lock_shared(),
                Access::Exclusive => lock.lock(),
            }
            .map_err(io(&lock_path))?;
        }
        let hints_path = root.join("hints.json");
        let map = fs::read(&hints_path)
            .ok()
            .and_then(|b| serde_json::from_slice::<BTreeMap<String, Hint>>(&b).ok())
            .unwrap_or_default();
        Ok(Cache {
            root: root.to_path_buf(),
            hints: Mutex::new(Hints { map, dirty: false }),
            _lock: lock,
            counter: AtomicU64::new(0),
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
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

    pub fn object_path(&self, hash: &str) -> PathBuf {
        let (a, b) = hash.split_at(2.min(hash.len()));
        self.root.join("objects").join(a).join(b)
    }

    /// Checks that an object exists with the right size and content (content
    /// by hint when possible). Err describes the problem.
    pub fn check_object(&self, hash: &str, bytes: u64) -> Result<(), String> {
        let p = self.object_path(hash);
        let md = fs::metadata(&p).map_err(|_| format!("object {} is missing", short(hash)))?;
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
        match key::hash_file(&p) {
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

    /// Reads a manifest; `None` if absent or unreadable (a miss).
    pub fn lookup(&self, key: &str) -> Option<Manifest> {
        let p = self.root.join("entries").join(format!("{key}.json"));
        let b = fs::read(p).ok()?;
        let m: Manifest = serde_json::from_slice(&b).ok()?;
        (m.schema == CACHE_SCHEMA && m.key == key).then_some(m)
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
    pub fn store_file(&self, staged: &Path) -> Result<(String, u64), CacheError> {
        let (hash, n) = key::hash_file(staged).map_err(io(staged))?;
        let dest = self.object_path(&hash);
        if fs::metadata(&dest).is_ok() && self.check_object(&hash, n).is_ok() {
            let _ = fs::remove_file(staged);
            return Ok((hash, n));
        }
        if let Some(parent) = dest.parent() {
            fs::create_dir_all(parent).map_err(io(parent))?;
        }
        let f = File::open(staged).map_err(io(staged))?;
        f.sync_all().map_err(io(staged))?;
        drop(f);
        fs::set_permissions(staged, fs::Permissions::from_mode(0o444)).map_err(io(staged))?;
        // A corrupted object in the way is replaced by the rename.
        if fs::rename(staged, &dest).is_err() {
            // Cross-device staging (should not happen: tmp/ is inside the cache): copy.
            let tmp = dest.with_extension(format!("tmp-{}", std::process::id()));
            fs::copy(staged, &tmp).map_err(io(&tmp))?;
            File::open(&tmp)
                .and_then(|f| f.sync_all())
                .map_err(io(&tmp))?;
            fs::rename(&tmp, &dest).map_err(io(&dest))?;
            let _ = fs::remove_file(staged);
        }
        Ok((hash, n))
    }

    /// Stores a staged output (file or directory) as objects.
    pub fn store_output(
        &self,
        staged: &Path,
        file_name: &str,
        dir: bool,
    ) -> Result<OutputRecord, CacheError> {
        if dir {
            let list = key::list_dir(staged).map_err(io(staged))?;
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

    /// Takes the per-key lock, calling `waiting` once if another process holds it.
    pub fn lock_key(&self, key: &str, waiting: &dyn Fn(&str)) -> Result<KeyLock, CacheError> {
        let p = self.root.join("locks").join(format!("{key}.lock"));
        let mut f = OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&p)
            .map_err(io(&p))?;
        if f.try_lock().is_err() {
            let holder = fs::read_to_string(&p).unwrap_or_default();
            waiting(holder.trim());
            f.lock().map_err(io(&p))?;
        }
        let _ = f.set_len(0);
        let _ = writeln!(f, "pid {}", std::process::id());
        Ok(KeyLock { _file: f })
    }

    /// A fresh staging directory for one stage run.
    pub fn staging(&self, key: &str) -> Result<Staging, CacheError> {
        let n = self.counter.fetch_add(1, Ordering::Relaxed);
        let p = self
            .root
            .join("tmp")
            .join(format!("{}-{n}-{}", std::process::id(), short(key)));
        let _ = remove_tree(&p);
        fs::create_dir_all(&p).map_err(io(&p))?;
        Ok(Staging { path: p })
    }

    /// Removes staging directories of processes that are gone.
    pub fn clean_tmp(&self) -> usize {
        let mut n = 0;
        if let Ok(rd) = fs::read_dir(self.root.join("tmp")) {
            for e in rd.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                let pid: Option<u32> = name.split('-').next().and_then(|s| s.parse().ok());
                if pid
                    .map(|p| p != std::process::id() && !pid_alive(p))
                    .unwrap_or(true)
                {
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
        fs::read(self.index_path(pipeline))
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

    /// Every manifest (key -> manifest); unreadable ones are listed separately.
    fn all_entries(&self) -> (BTreeMap<String, (Manifest, u64)>, Vec<PathBuf>) {
        let mut ok = BTreeMap::new();
        let mut bad = Vec::new();
        if let Ok(rd) = fs::read_dir(self.root.join("entries")) {
            for e in rd.flatten() {
                let p = e.path();
                let name = e.file_name().to_string_lossy().into_owned();
                let Some(key) = name.strip_suffix(".json") else {
                    bad.push(p); // temporary leftovers
                    continue;
                };
                let mtime = e.metadata().map(|m| m.mtime() as u64).unwrap_or(0);
                match fs::read(&p)
                    .ok()
                    .and_then(|b| serde_json::from_slice::<Manifest>(&b).ok())
                {
                    Some(m) if m.key == key && m.schema == CACHE_SCHEMA => {
                        ok.insert(key.to_string(), (m, mtime));
                    }
                    _ => bad.push(p),
                }
            }
        }
        (ok, bad)
    }

    fn all_objects(&self) -> Vec<(String, PathBuf, u64)> {
        let mut out = Vec::new();
        if let Ok(rd) = fs::read_dir(self.root.join("objects")) {
            for d in rd.flatten() {
                let a = d.file_name().to_string_lossy().into_owned();
                if let Ok(rd2) = fs::read_dir(d.path()) {
                    for e in rd2.flatten() {
                        let b = e.file_name().to_string_lossy().into_owned();
                        let n = e.metadata().map(|m| m.len()).unwrap_or(0);
                        out.push((format!("{a}{b}"), e.path(), n));
                    }
                }
            }
        }
        out.sort();
        out
    }

    /// Rehashes every object; drops corrupted objects and every entry that
    /// uses one, and unreadable manifests.
    pub fn verify(&self) -> VerifyReport {
        let mut rep = VerifyReport::default();
        let objects = self.all_objects();
        let mut bad_objects = BTreeSet::new();
        for (name, path, _) in &objects {
            rep.objects_checked += 1;
            let good = matches!(key::hash_file(path), Ok((h, _)) if &h == name);
            if good {
                if let Ok(md) = fs::metadata(path) {
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
        for p in bad {
            if p.extension().map(|e| e == "json").unwrap_or(false) {
                rep.broken_manifests.push(p.display().to_string());
            }
            let _ = fs::remove_file(p);
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
        for p in bad {
            let _ = fs::remove_file(p);
        }
        // Entries the indexes point at were used by the latest run of some stage.
        let mut indexed = BTreeSet::new();
        if let Ok(rd) = fs::read_dir(self.root.join("index")) {
            for e in rd.flatten() {
                if let Some(ix) = fs::read(e.path())
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
        for (name, path, n) in self.all_objects() {
            if !referenced.contains(name.as_str()) {
                let _ = fs::remove_file(&path);
                rep.objects_removed += 1;
                rep.bytes_freed += n;
            } else {
                rep.bytes_kept += n;
            }
        }
        // Under the exclusive lock no one holds key locks: drop the files.
        if let Ok(rd) = fs::read_dir(self.root.join("locks")) {
            for e in rd.flatten() {
                let _ = fs::remove_file(e.path());
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
    pub bytes_freed: u64,
    pub bytes_kept: u64,
    pub tmp_removed: usize,
}

#[derive(Debug, Default, Clone, Serialize)]
pub struct VerifyReport {
    pub objects_checked: usize,
    pub entries_checked: usize,
    pub corrupted_objects: Vec<String>,
    pub dropped_entries: Vec<String>,
    pub broken_manifests: Vec<String>,
}

impl VerifyReport {
    pub fn clean(&self) -> bool {
        self.corrupted_objects.is_empty()
            && self.dropped_entries.is_empty()
            && self.broken_manifests.is_empty()
    }
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

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("2048").unwrap(), 2048);
        assert_eq!(parse_size("1K").unwrap(), 1024);
        assert_eq!(parse_size("1.5G").unwrap(), 3 << 29);
        assert!(parse_size("12Q").is_err());
    }
}
