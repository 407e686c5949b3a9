//! VDA 5050 JSON schemas from a folder (`--vda-schemas DIR`), checked with the
//! `jsonschema` crate on every message read and written, beside [`crate::msg`]'s own
//! rules: give it the official schemas of the version spoken (the VDA 5050
//! repository's `json_schemas/`, or `vda-5050-cli`'s `schema/vX.Y/`).
//!
//! A file is a topic's schema by its name: `order.schema`, `order.schema.json`,
//! `order.json`, and for `instantActions` also `instant-actions.*`. References between
//! the files (`$ref` to another file's `$id`) resolve among them; nothing is fetched.

use crate::VdaFail;
use jsonschema::{Retrieve, Uri, Validator};
use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The topics a schema may be given for.
pub const TOPICS: [&str; 6] = [
    "order",
    "instantActions",
    "state",
    "connection",
    "visualization",
    "factsheet",
];

/// The files of the folder, by `$id`, for `$ref`s between them.
struct Folder(HashMap<String, Value>);

impl Retrieve for Folder {
    fn retrieve(
        &self,
        uri: &Uri<String>,
    ) -> Result<Value, Box<dyn std::error::Error + Send + Sync>> {
        self.0.get(uri.as_str()).cloned().ok_or_else(|| {
            format!("{uri} is not among the schemas given (nothing is fetched)").into()
        })
    }
}

/// Compiled schemas, by topic.
pub struct Schemas {
    dir: PathBuf,
    by_topic: HashMap<&'static str, Validator>,
}

impl std::fmt::Debug for Schemas {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Schemas")
            .field("dir", &self.dir)
            .field("topics", &self.topics())
            .finish()
    }
}

fn kebab(topic: &str) -> String {
    let mut out = String::new();
    for c in topic.chars() {
        if c.is_ascii_uppercase() {
            out.push('-');
            out.push(c.to_ascii_lowercase());
        } else {
            out.push(c);
        }
    }
    out
}

impl Schemas {
    /// Reads every `*.json` and `*.schema` file of `dir` and compiles the topics' ones;
    /// at least one topic must be there.
    pub fn load(dir: &Path) -> Result<Self, VdaFail> {
        let bad =
            |what: String| VdaFail::Config(format!("--vda-schemas {}: {what}", dir.display()));
        let entries = std::fs::read_dir(dir).map_err(|e| bad(e.to_string()))?;
        let mut files: HashMap<String, Value> = HashMap::new();
        for e in entries.flatten() {
            let path = e.path();
            let name = e.file_name().to_string_lossy().to_string();
            if !(name.ends_with(".json") || name.ends_with(".schema")) {
                continue;
            }
            let text = std::fs::read_to_string(&path).map_err(|e| bad(format!("{name}: {e}")))?;
            let value: Value =
                serde_json::from_str(&text).map_err(|e| bad(format!("{name}: {e}")))?;
            files.insert(name, value);
        }
        let by_id: HashMap<String, Value> = files
            .values()
            .filter_map(|v| Some((v.get("$id")?.as_str()?.to_string(), v.clone())))
            .collect();
        let folder = std::sync::Arc::new(Folder(by_id));
        let mut by_topic = HashMap::new();
        for topic in TOPICS {
            let names: Vec<String> = [topic.to_string(), kebab(topic)]
                .iter()
                .flat_map(|t| {
                    [
                        format!("{t}.schema"),
                        format!("{t}.schema.json"),
                        format!("{t}.json"),
                    ]
                })
                .collect();
            let Some((name, schema)) = names.iter().find_map(|n| files.get(n).map(|v| (n, v)))
            else {
                continue;
            };
            let validator = jsonschema::options()
                .with_retriever(FolderRef(folder.clone()))
                .build(schema)
                .map_err(|e| bad(format!("{name}: {e}")))?;
            by_topic.insert(topic, validator);
        }
        if by_topic.is_empty() {
            return Err(bad(format!(
                "no VDA 5050 schema in it (looked for {} as NAME.schema, NAME.schema.json, NAME.json)",
                TOPICS.join(", ")
            )));
        }
        Ok(Schemas {
            dir: dir.to_path_buf(),
            by_topic,
        })
    }

    /// The topics with a schema.
    pub fn topics(&self) -> Vec<&'static str> {
        let mut t: Vec<_> = self.by_topic.keys().copied().collect();
        t.sort_unstable();
        t
    }

    /// Checks one message of `topic` (a topic without a schema passes); the first
    /// three violations, each with where it is, when it does not.
    pub fn check(&self, topic: &str, message: &Value) -> Result<(), String> {
        let Some(v) = self.by_topic.get(topic) else {
            return Ok(());
        };
        let errors: Vec<String> = v
            .iter_errors(message)
            .take(3)
            .map(|e| format!("{} at {:?}", e, e.instance_path().to_string()))
            .collect();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(format!(
                "{topic} breaks its JSON schema: {}",
                errors.join("; ")
            ))
        }
    }

    /// Checks a message's bytes (JSON) of `topic`.
    pub fn check_bytes(&self, topic: &str, bytes: &[u8]) -> Result<(), String> {
        if !self.by_topic.contains_key(topic) {
            return Ok(());
        }
        let v: Value = serde_json::from_slice(bytes).map_err(|e| format!("not JSON: {e}"))?;
        self.check(topic, &v)
    }
}

/// The folder, shared by every topic's validator.
struct FolderRef(std::sync::Arc<Folder>);

impl Retrieve for FolderRef {
    fn retrieve(
        &self,
        uri: &Uri<String>,
    ) -> Result<Value, Box<dyn std::error::Error + Send + Sync>> {
        self.0.retrieve(uri)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn dir(files: &[(&str, Value)]) -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "muster-vda-schemas-{}-{}",
            std::process::id(),
            files.len()
        ));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        for (n, v) in files {
            std::fs::write(d.join(n), v.to_string()).unwrap();
        }
        d
    }

    #[test]
    fn topics_are_found_by_name_refs_resolve_among_the_files_and_violations_say_where() {
        let common = serde_json::json!({
            "$schema": "http://json-schema.org/draft-07/schema#",
            "$id": "http://example.org/common.schema.json",
            "definitions": {"header": {"type": "object", "required": ["headerId"],
                "properties": {"headerId": {"type": "integer", "minimum": 0}}}}
        });
        let state = serde_json::json!({
            "$schema": "http://json-schema.org/draft-07/schema#",
            "allOf": [{"$ref": "http://example.org/common.schema.json#/definitions/header"},
                      {"properties": {"batteryState": {"properties":
                          {"batteryCharge": {"type": "number", "maximum": 100}}}}}]
        });
        let actions = serde_json::json!({"type": "object", "required": ["instantActions"]});
        let d = dir(&[
            ("common.schema.json", common),
            ("state.schema", state),
            ("instant-actions.schema.json", actions),
            ("README.md", Value::Null),
        ]);
        let s = Schemas::load(&d).unwrap();
        assert_eq!(s.topics(), ["instantActions", "state"]);
        let ok = serde_json::json!({"headerId": 3, "batteryState": {"batteryCharge": 80}});
        s.check("state", &ok).unwrap();
        let e = s
            .check(
                "state",
                &serde_json::json!({"headerId": -1, "batteryState": {"batteryCharge": 140}}),
            )
            .unwrap_err();
        assert!(
            e.contains("/headerId") && e.contains("/batteryState/batteryCharge"),
            "{e}"
        );
        assert!(s
            .check_bytes("instantActions", b"{}")
            .unwrap_err()
            .contains("instantActions"));
        // No schema for a topic: it passes.
        s.check("order", &serde_json::json!(1)).unwrap();
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_folder_without_schemas_or_with_a_bad_one_is_refused() {
        let d = dir(&[("notes.json", serde_json::json!({"a": 1}))]);
        assert!(Schemas::load(&d)
            .unwrap_err()
            .to_string()
            .contains("no VDA 5050 schema"));
        let _ = std::fs::remove_dir_all(&d);
        let d = dir(&[
            ("x.json", serde_json::json!(1)),
            (
                "order.json",
                serde_json::json!({"$ref": "http://nowhere.example/x.json"}),
            ),
        ]);
        let e = Schemas::load(&d).unwrap_err().to_string();
        assert!(e.contains("order.json"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
