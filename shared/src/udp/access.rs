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
//! connect but sees and gets nothing.
//!
//! ```text
//! # web NAME SHA-256-HEX: the user may also sign in to `muster web` with a token
//! web alice 9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08
//! ```
//! A `web` line names a user of a `user` or `operator` line (before or after it) and
//! holds the SHA-256 of its web token ([`web_token_hash`]), never the token: the token
//! is 160 random bits, so a fast hash is as strong as a slow one and the file read
//! does not give a way in. The broker's UDP front ignores `web` lines. An operator's actions (status, withdraw, end a
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
    /// The SHA-256 of the user's web token (a `web` line), if it may sign in on the web.
    pub web: Option<[u8; 32]>,
    set: GlobSet,
}

impl Policy {
    /// Whether the service id matches one of the user's patterns.
    pub fn allows(&self, service: &str) -> bool {
        self.set.is_match(service)
    }

    /// Whether `token` is the user's web token (in time independent of where they
    /// differ); false for a user with no `web` line.
    pub fn web_token_matches(&self, token: &str) -> bool {
        let Some(want) = self.web else { return false };
        let got = web_token_hash(token);
        want.iter()
            .zip(got.iter())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
    }
}

/// The hash a `web` line holds for a web token: SHA-256 over a domain-separating prefix
/// and the token.
pub fn web_token_hash(token: &str) -> [u8; 32] {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(b"muster web token v1\0");
    h.update(token.as_bytes());
    h.finalize().into()
}

/// A new web token: 160 random bits as 40 hex digits.
pub fn new_web_token() -> String {
    let mut b = [0u8; 20];
    rand::fill(&mut b);
    hex::encode(b)
}

/// The access file's `web` line for a token.
pub fn web_line(name: &str, token: &str) -> String {
    format!("web {name} {}", hex::encode(web_token_hash(token)))
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
        let mut webs: Vec<(usize, String, [u8; 32])> = Vec::new();
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
                Some("web") => {
                    let name = words.next().ok_or_else(|| at("missing user name".into()))?;
                    let hash = words
                        .next()
                        .ok_or_else(|| at("missing the web token's hash".into()))?;
                    let mut h = [0u8; 32];
                    hex::decode_to_slice(hash, &mut h).map_err(|_| {
                        at(format!(
                            "bad web token hash {hash:?}: 64 hex digits (a SHA-256)"
                        ))
                    })?;
                    if words.next().is_some() {
                        return Err(at("a web line is `web NAME HASH`".into()));
                    }
                    webs.push((i + 1, name.to_string(), h));
                    continue;
                }
                Some(w) => {
                    return Err(at(format!(
                        "unknown directive {w:?} (expected `user`, `operator` or `web`)"
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
                        web: None,
                        set,
                    },
                )
                .is_some()
            {
                return Err(at(format!("user {name:?} appears twice")));
            }
        }
        for (line, name, hash) in webs {
            let policy = users.get_mut(&name).ok_or_else(|| {
                format!("line {line}: web line for {name:?}, who has no user or operator line")
            })?;
            if policy.web.replace(hash).is_some() {
                return Err(format!("line {line}: a second web line for {name:?}"));
            }
        }
        Ok(AccessFile { users })
    }

    /// Every listed user's name and policy.
    pub fn users(&self) -> impl Iterator<Item = (&str, &Policy)> {
        self.users.iter().map(|(n, p)| (n.as_str(), p))
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
    fn web_lines_give_a_user_a_token_and_only_its_hash_is_kept() {
        let token = new_web_token();
        assert_eq!(token.len(), 40);
        assert_ne!(token, new_web_token(), "random");
        let text = format!(
            "{}\nuser alice {K} T1/*\nuser bob {K} *\n",
            web_line("alice", &token)
        );
        assert!(!text.contains(&token), "the file holds only the hash");
        let f = AccessFile::parse(&text).unwrap();
        let a = f.get("alice").unwrap();
        assert!(a.web_token_matches(&token));
        assert!(!a.web_token_matches(&new_web_token()));
        assert!(!a.web_token_matches(""));
        let b = f.get("bob").unwrap();
        assert!(
            b.web.is_none() && !b.web_token_matches(&token),
            "no web line: no sign-in"
        );
        let orphan = AccessFile::parse(&web_line("carol", &token)).unwrap_err();
        assert!(
            orphan.contains("line 1") && orphan.contains("no user"),
            "{orphan}"
        );
        let twice = format!(
            "user alice {K}\n{}\n{}\n",
            web_line("alice", "a"),
            web_line("alice", "b")
        );
        assert!(AccessFile::parse(&twice)
            .unwrap_err()
            .contains("second web line"));
        assert!(
            AccessFile::parse(&format!("user alice {K}\nweb alice 12ab\n"))
                .unwrap_err()
                .contains("64 hex digits")
        );
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
