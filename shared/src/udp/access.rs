//! The broker's access file: who may connect over UDP, with which public key, and which
//! services each user may list and request. Missing policy means deny.
//!
//! ```text
//! # user NAME PUBLIC-KEY-HEX PATTERN...
//! user alice 3b6a27bcceb6a42d62a3a8d02a6f0d73653215771de243a63ac048a18b59da29 T1/* D1/goto
//! user bob   8f1d...                                                         *
//! # operator NAME PUBLIC-KEY-HEX PATTERN...: a user who may also act as an operator
//! operator carol 5e0c...                                                     *
//! ```
//! Patterns are globs over service ids (`system/service`); a user with no pattern may
//! connect but sees and gets nothing. An operator's actions (status, withdraw, end a
//! session, drop a user, move or drop a queued request) reach the whole broker; its
//! patterns still decide what it lists and requests as a user.

use globset::{Glob, GlobSet, GlobSetBuilder};
use std::collections::HashMap;
use std::path::Path;

/// What one user may do.
#[derive(Clone, Debug)]
pub struct Policy {
    /// The user's public key.
    pub key: [u8; 32],
    /// The patterns, as written.
    pub patterns: Vec<String>,
    /// Whether the line was an `operator` line: the user may act as an operator.
    pub operator: bool,
    set: GlobSet,
}

impl Policy {
    /// Whether the service id matches one of the user's patterns.
    pub fn allows(&self, service: &str) -> bool {
        self.set.is_match(service)
    }
}

/// A parsed access file.
#[derive(Clone, Debug, Default)]
pub struct AccessFile {
    users: HashMap<String, Policy>,
}

/// Longest remote user name.
pub const MAX_USER_NAME: usize = 24;

/// Checks a remote user name: 1 to 24 characters of `[A-Za-z0-9_-]`.
pub fn valid_user_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_USER_NAME
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// The line `muster keygen` prints for the broker's access file (`operator`: the
/// user may act as an operator).
pub fn access_line(name: &str, public: &[u8; 32], patterns: &[String], operator: bool) -> String {
    let role = if operator { "operator" } else { "user" };
    let mut line = format!("{role} {name} {}", hex::encode(public));
    for p in patterns {
        line.push(' ');
        line.push_str(p);
    }
    line
}

impl AccessFile {
    /// Reads and parses the file at `path`.
    pub fn load(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("access file {}: {e}", path.display()))?;
        Self::parse(&text).map_err(|e| format!("access file {}: {e}", path.display()))
    }

    /// Parses an access file's text; errors name the line.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut users = HashMap::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let at = |e: String| format!("line {}: {e}", i + 1);
            let mut words = line.split_whitespace();
            let operator = match words.next() {
                Some("user") => false,
                Some("operator") => true,
                Some(w) => {
                    return Err(at(format!(
                        "unknown directive {w:?} (expected `user` or `operator`)"
                    )))
                }
                None => continue,
            };
            let name = words.next().ok_or_else(|| at("missing user name".into()))?;
            if !valid_user_name(name) {
                return Err(at(format!(
                    "bad user name {name:?}: 1 to {MAX_USER_NAME} of [A-Za-z0-9_-]"
                )));
            }
            let key = words
                .next()
                .ok_or_else(|| at("missing public key".into()))?;
            let key = super::crypto::parse_key(key).map_err(at)?;
            let mut b = GlobSetBuilder::new();
            let mut patterns = Vec::new();
            for p in words {
                b.add(Glob::new(p).map_err(|e| at(format!("bad pattern {p:?}: {e}")))?);
                patterns.push(p.to_string());
            }
            let set = b.build().map_err(|e| at(e.to_string()))?;
            if users
                .insert(
                    name.to_string(),
                    Policy {
                        key,
                        patterns,
                        operator,
                        set,
                    },
                )
                .is_some()
            {
                return Err(at(format!("user {name:?} appears twice")));
            }
        }
        Ok(AccessFile { users })
    }

    /// The policy of `name`, if the file lists it.
    pub fn get(&self, name: &str) -> Option<&Policy> {
        self.users.get(name)
    }

    /// Number of users listed.
    pub fn len(&self) -> usize {
        self.users.len()
    }

    /// Whether no user is listed.
    pub fn is_empty(&self) -> bool {
        self.users.is_empty()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const K: &str = "3b6a27bcceb6a42d62a3a8d02a6f0d73653215771de243a63ac048a18b59da29";

    #[test]
    fn parses_users_and_matches_patterns() {
        let f = AccessFile::parse(&format!(
            "# comment\nuser alice {K} T1/* D1/goto  # trailing\n\nuser bob {K}\nuser carol {K} *\n"
        ))
        .unwrap();
        assert_eq!(f.len(), 3);
        let a = f.get("alice").unwrap();
        assert!(a.allows("T1/camera"));
        assert!(a.allows("D1/goto"));
        assert!(!a.allows("D1/status"));
        assert!(!a.allows("T2/camera"));
        assert!(
            !f.get("bob").unwrap().allows("T1/camera"),
            "no pattern: deny"
        );
        assert!(f.get("carol").unwrap().allows("anything/at-all"));
        assert!(f.get("dave").is_none());
        assert!(!a.operator && !f.get("carol").unwrap().operator);
    }

    #[test]
    fn operator_lines_make_operators() {
        let f = AccessFile::parse(&format!("operator olga {K} T1/*\nuser ursula {K} *\n")).unwrap();
        let o = f.get("olga").unwrap();
        assert!(o.operator);
        assert!(
            o.allows("T1/camera") && !o.allows("D1/goto"),
            "patterns still apply"
        );
        assert!(!f.get("ursula").unwrap().operator);
        // A name is one line, whichever its role.
        assert!(AccessFile::parse(&format!("user a {K}\noperator a {K}\n"))
            .unwrap_err()
            .contains("twice"));
        let key = super::super::crypto::parse_key(K).unwrap();
        let line = access_line("olga", &key, &["T1/*".into()], true);
        assert_eq!(line, format!("operator olga {K} T1/*"));
        assert!(
            AccessFile::parse(&line)
                .unwrap()
                .get("olga")
                .unwrap()
                .operator
        );
    }

    #[test]
    fn errors_name_the_line() {
        let e = AccessFile::parse(&format!("user alice {K}\nuser al!ce {K}\n")).unwrap_err();
        assert!(e.starts_with("line 2:"), "{e}");
        assert!(AccessFile::parse("user bob 1234\n")
            .unwrap_err()
            .contains("line 1"));
        assert!(AccessFile::parse("allow x\n")
            .unwrap_err()
            .contains("unknown directive"));
        assert!(AccessFile::parse(&format!("user a {K}\nuser a {K}\n"))
            .unwrap_err()
            .contains("twice"));
        assert!(AccessFile::parse(&format!("user a {K} [\n"))
            .unwrap_err()
            .contains("pattern"));
    }
}
