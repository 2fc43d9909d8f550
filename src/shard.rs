//! Shards: one sweep split over machines that share no cache.
//!
//! A sweep runs its variants on one cache, and a suite from an empty cache can
//! take longer than a machine is lent for (the benchmark suite: about three
//! hours on two cores). `fure sweep P --shard K/N` runs only the variants whose
//! index is `K - 1` modulo `N` and writes their part of the record to
//! `<out>/<pipeline>/shards/K-of-N.json`, running no aggregate and publishing
//! nothing; the shards may run anywhere, one after another or at once, each on
//! its own cache. `fure sweep P --merge FILE...` then reads the `N` shard files
//! (kept in the repository, say, where the machines that made them are gone),
//! checks that they are one sweep and all of it, writes the sweep's record
//! `<out>/<pipeline>/sweep.json` from them and runs the aggregates and
//! `[publish]` on it as the whole sweep would have. The merged record holds the
//! same variants, in the same order, with the same settings, statuses and
//! metrics a single sweep on one machine writes; only the `costs` (seconds,
//! memory, load) are each shard machine's own.
//!
//! # A shard file
//!
//! The sweep record of the shard's variants ([`crate::sweep::record`]) with one
//! more field:
//!
//! ```json
//! {"shard": {"k": 1, "n": 3, "variants": 27, "fingerprint": "<blake3 hex>",
//!            "origin": {"revision": "<git>", "dirty": false, "date": "2026-12-02 14:00 UTC",
//!                       "machine": "AMD EPYC (2 cores, 24 GiB, linux x86_64)",
//!                       "command": "fure sweep pipelines/benchmark.toml --shard 1/3 --jobs 1"}},
//!  "pipeline": "benchmark", "crossed": {...}, "each": {...}, "each_order": [...],
//!  "variants": [...]}
//! ```
//!
//! # When shards are one sweep
//!
//! The [`fingerprint`] hashes, for every variant of the whole sweep (every
//! shard's, in order), each stage's name, kind, implementation version and
//! keyed parameters, and its inputs: an input file's content hash, an upstream
//! output by stage and port name. That is the stage's cache key with the
//! upstream outputs named instead of hashed, so two shards with the same
//! fingerprint computed every stage from the same declared inputs with the
//! same implementation version: by the rule the cache itself rests on (a change
//! in what a stage computes bumps its version), their outputs are the ones one
//! machine would have made. The git revisions may differ (a later commit that
//! changed no stage); they are provenance, listed in the published stamp, and
//! a shard made from a tree with uncommitted changes is refused, since nothing
//! could say what it ran. The merge recomputes the fingerprint from the
//! pipeline as it is given (with its `--grid`, `--each`, `--set`), so a shard of
//! another sweep, a pipeline edited since, or a stage whose version moved
//! since is an error naming the file. Shard files are untrusted input: every
//! field is checked, and an error names the file and the field.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::json;

use crate::cache::Cache;
use crate::exec::keyed_params;
use crate::key::Preimage;
use crate::plan::{Plan, Source};
use crate::publish::Origin;

/// Shard `k` of `n` (1-based): the variants whose index is `k - 1` modulo `n`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub k: usize,
    pub n: usize,
}

impl std::str::FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Shard, String> {
        let bad = || format!("`{s}`: expected K/N with 1 <= K <= N (e.g. 2/3)");
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let (k, n) = (
            k.trim().parse::<usize>().map_err(|_| bad())?,
            n.trim().parse::<usize>().map_err(|_| bad())?,
        );
        if k == 0 || k > n {
            return Err(bad());
        }
        Ok(Shard { k, n })
    }
}

impl Shard {
    /// Whether variant `index` belongs to this shard.
    pub fn holds(self, index: usize) -> bool {
        index % self.n == self.k - 1
    }
    /// The shard file's name, `K-of-N.json`.
    pub fn file_name(self) -> String {
        format!("{}-of-{}.json", self.k, self.n)
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.k, self.n)
    }
}

/// Why shards could not be fingerprinted or merged.
#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    #[error("{file}: {why}")]
    File { file: String, why: String },
    #[error("{0}")]
    Set(String),
}

fn file_error(file: &Path, why: impl Into<String>) -> ShardError {
    ShardError::File {
        file: file.display().to_string(),
        why: why.into(),
    }
}

/// The fingerprint of a whole sweep: its variants' plans, in order (module docs).
pub fn fingerprint(plans: &[Plan], cache: &Cache) -> Result<String, ShardError> {
    let mut h = blake3::Hasher::new();
    h.update(b"fure-sweep-fingerprint-v1\0");
    for (v, plan) in plans.iter().enumerate() {
        h.update(format!("variant {v}\0").as_bytes());
        for st in &plan.stages {
            let mut inputs = BTreeMap::new();
            for inp in &st.inputs {
                let named = match &inp.source {
                    Source::Upstream { stage, port } => {
                        format!("upstream:{}:{port}", plan.stages[*stage].name)
                    }
                    Source::Path { path, written } => {
                        let (hash, _, _) = cache.hash_source(path).map_err(|e| {
                            ShardError::Set(format!(
                                "stage `{}`, input `{}`: cannot read `{written}`: {e}",
                                st.name, inp.port
                            ))
                        })?;
                        format!("file:{hash}")
                    }
                };
                inputs.insert(inp.port.clone(), named);
            }
            let key = Preimage::new(&st.kind, st.version, &keyed_params(st), inputs).key();
            h.update(format!("{}\0{key}\0", st.name).as_bytes());
        }
    }
    Ok(h.finalize().to_hex().to_string())
}

/// A shard's record: the sweep record of its variants with the `shard` field.
pub fn shard_record(
    mut record: serde_json::Value,
    shard: Shard,
    total: usize,
    fingerprint: &str,
    origin: &Origin,
) -> serde_json::Value {
    record["shard"] = json!({
        "k": shard.k,
        "n": shard.n,
        "variants": total,
        "fingerprint": fingerprint,
        "origin": {
            "revision": origin.revision,
            "dirty": origin.dirty,
            "date": origin.date,
            "machine": origin.machine,
            "command": origin.command,
        },
    });
    record
}

/// The merged shards: the whole sweep's variants (record entries, in index
/// order) and where each shard was made, in shard order.
#[derive(Debug)]
pub struct Merged {
    pub variants: Vec<serde_json::Value>,
    pub origins: Vec<(Shard, Origin)>,
}

/// Reads and checks the shard files against the sweep they must make up:
/// `pipeline`'s name, the settings of every variant (`expected`, in index
/// order, as the record writes them) and its [`fingerprint`].
pub fn merge(
    files: &[&Path],
    pipeline: &str,
    expected: &[serde_json::Value],
    fingerprint: &str,
) -> Result<Merged, ShardError> {
    let total = expected.len();
    let mut n_seen: Option<(usize, String)> = None;
    let mut by_k: BTreeMap<usize, (String, Origin, Vec<serde_json::Value>)> = BTreeMap::new();
    for &file in files {
        let bytes = std::fs::read(file).map_err(|e| file_error(file, e.to_string()))?;
        let doc: serde_json::Value = serde_json::from_slice(&bytes)
            .map_err(|e| file_error(file, format!("not JSON: {e}")))?;
        let field = |name: &str| -> Result<&serde_json::Value, ShardError> {
            doc.pointer(name)
                .ok_or_else(|| file_error(file, format!("`{}`: missing", &name[1..])))
        };
        let count = |name: &str| -> Result<usize, ShardError> {
            field(name)?
                .as_u64()
                .map(|x| x as usize)
                .ok_or_else(|| file_error(file, format!("`{}`: expected a count", &name[1..])))
        };
        let text = |name: &str| -> Result<String, ShardError> {
            field(name)?
                .as_str()
                .map(str::to_string)
                .ok_or_else(|| file_error(file, format!("`{}`: expected text", &name[1..])))
        };
        let name = text("/pipeline")?;
        if name != pipeline {
            return Err(file_error(
                file,
                format!("`pipeline`: a shard of `{name}`, not of `{pipeline}`"),
            ));
        }
        let (k, n) = (count("/shard/k")?, count("/shard/n")?);
        if k == 0 || k > n {
            return Err(file_error(file, format!("`shard`: {k}/{n} is no shard")));
        }
        let shard = Shard { k, n };
        let variants = count("/shard/variants")?;
        if variants != total {
            return Err(file_error(
                file,
                format!(
                    "`shard.variants`: a sweep of {variants} variants, where the pipeline as \
                     given has {total}"
                ),
            ));
        }
        if text("/shard/fingerprint")? != fingerprint {
            return Err(file_error(
                file,
                "`shard.fingerprint`: made from another sweep (a stage's kind, version, \
                 parameters or input files differ from the pipeline as given here, with its \
                 --grid, --each and --set); rerun that shard from this one",
            ));
        }
        let origin = Origin {
            revision: text("/shard/origin/revision")?,
            dirty: field("/shard/origin/dirty")?
                .as_bool()
                .ok_or_else(|| file_error(file, "`shard.origin.dirty`: expected true or false"))?,
            date: text("/shard/origin/date")?,
            machine: text("/shard/origin/machine")?,
            command: text("/shard/origin/command")?,
        };
        if origin.dirty {
            return Err(file_error(
                file,
                format!(
                    "`shard.origin.dirty`: made from a tree with uncommitted changes at {}; \
                     nothing can say what it ran: rerun shard {shard} from a clean checkout",
                    origin.revision
                ),
            ));
        }
        match &n_seen {
            Some((seen, other)) if *seen != n => {
                return Err(file_error(
                    file,
                    format!("`shard.n`: shard {shard}, where {other} splits the sweep in {seen}"),
                ))
            }
            None => n_seen = Some((n, file.display().to_string())),
            _ => {}
        }
        let list = field("/variants")?
            .as_array()
            .ok_or_else(|| file_error(file, "`variants`: expected an array"))?;
        let mut mine = Vec::with_capacity(list.len());
        for (j, v) in list.iter().enumerate() {
            let at = |why: String| file_error(file, format!("`variants[{j}]`: {why}"));
            let index = v
                .get("index")
                .and_then(|x| x.as_u64())
                .map(|x| x as usize)
                .ok_or_else(|| at("`index`: expected a count".into()))?;
            if index >= total || !shard.holds(index) {
                return Err(at(format!("variant {index} is not one of shard {shard}'s")));
            }
            check_variant(v, index, pipeline, &expected[index]).map_err(at)?;
            mine.push(v.clone());
        }
        let want = (0..total).filter(|&i| shard.holds(i)).count();
        let mut indices: Vec<usize> = mine
            .iter()
            .map(|v| v["index"].as_u64().unwrap_or(0) as usize)
            .collect();
        indices.sort_unstable();
        indices.dedup();
        if indices.len() != want || mine.len() != want {
            return Err(file_error(
                file,
                format!(
                    "`variants`: shard {shard} holds {} distinct of its {want} variants (an \
                     interrupted shard writes no file: was it edited?)",
                    indices.len()
                ),
            ));
        }
        if let Some((other, _, _)) = by_k.get(&k) {
            return Err(file_error(
                file,
                format!("`shard`: shard {shard} is also given as {other}"),
            ));
        }
        by_k.insert(k, (file.display().to_string(), origin, mine));
    }
    let n = n_seen.map_or(0, |(n, _)| n);
    let missing: Vec<String> = (1..=n)
        .filter(|k| !by_k.contains_key(k))
        .map(|k| format!("{k}/{n}"))
        .collect();
    if n == 0 || !missing.is_empty() {
        return Err(ShardError::Set(format!(
            "shards missing: {} (run `fure sweep PIPELINE --shard K/N` for each; every shard of \
             the sweep is needed)",
            if n == 0 {
                "all".into()
            } else {
                missing.join(", ")
            }
        )));
    }
    let mut variants: Vec<serde_json::Value> = Vec::with_capacity(total);
    let mut origins = Vec::with_capacity(n);
    for (k, (_, origin, mine)) in by_k {
        origins.push((Shard { k, n }, origin));
        variants.extend(mine);
    }
    variants.sort_by_key(|v| v["index"].as_u64().unwrap_or(0));
    Ok(Merged { variants, origins })
}

/// One record entry of a shard against the variant the sweep has at `index`.
fn check_variant(
    v: &serde_json::Value,
    index: usize,
    pipeline: &str,
    expected_settings: &serde_json::Value,
) -> Result<(), String> {
    let name = format!("{pipeline}@v{index}");
    if v.get("name").and_then(|x| x.as_str()) != Some(name.as_str()) {
        return Err(format!("`name`: expected \"{name}\""));
    }
    if v.get("settings") != Some(expected_settings) {
        return Err(format!(
            "`settings`: not variant {index}'s settings in the pipeline as given ({expected_settings})"
        ));
    }
    match v.get("status").and_then(|x| x.as_str()) {
        Some("ok" | "degraded" | "failed") => {}
        _ => return Err("`status`: expected \"ok\", \"degraded\" or \"failed\"".into()),
    }
    let metrics = v
        .get("metrics")
        .and_then(|m| m.as_object())
        .ok_or("`metrics`: expected an object of numbers")?;
    if let Some((k, _)) = metrics.iter().find(|(_, x)| !x.is_number()) {
        return Err(format!("`metrics.{k}`: expected a number"));
    }
    if !v.get("costs").is_some_and(|c| c.is_object()) {
        return Err("`costs`: expected an object".into());
    }
    Ok(())
}

/// The line the published documents' stamp gains: which shard was made where.
pub fn provenance(origins: &[(Shard, Origin)]) -> String {
    let parts: Vec<String> = origins
        .iter()
        .map(|(s, o)| {
            format!(
                "shard {s} by `{}` at revision {} on {}, {}",
                o.command, o.revision, o.machine, o.date
            )
        })
        .collect();
    format!("Its variants ran in shards: {}.", parts.join("; "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_split_every_index_once() {
        assert_eq!("2/3".parse::<Shard>(), Ok(Shard { k: 2, n: 3 }));
        for bad in ["0/3", "4/3", "3", "a/b", "1/0"] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
        let n = 4;
        for i in 0..11 {
            let owners = (1..=n).filter(|&k| Shard { k, n }.holds(i)).count();
            assert_eq!(owners, 1, "variant {i}");
        }
        assert_eq!(Shard { k: 1, n: 3 }.file_name(), "1-of-3.json");
    }
}
