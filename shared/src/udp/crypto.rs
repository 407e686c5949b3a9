//! Keys, the Noise handshake, replay windows, session ciphers and stateless cookies.
//!
//! Nothing here is home-made cryptography: the user ↔ broker channel is a Noise XX
//! handshake (`snow`), then Noise transport messages with explicit nonces; the
//! user ↔ system channel is ChaCha20-Poly1305 (RustCrypto) under a random 256-bit key
//! the broker hands to both ends over channels it already authenticated (a Kerberos-style
//! ticket); address-validation tokens are HMAC-SHA-256 over the client's address.

use chacha20poly1305::aead::{Aead, KeyInit, Payload as AeadPayload};
use chacha20poly1305::{ChaCha20Poly1305, Key, Nonce};
use hmac::{Hmac, Mac};
use sha2::Sha256;
use std::net::SocketAddr;
use std::path::Path;

/// Noise handshake state, re-exported for the transports.
pub use snow::HandshakeState;

/// The Noise protocol the user ↔ broker channel runs: mutual authentication by static
/// keys, the broker's key learned in the handshake (and checked if the user pins it).
pub const NOISE_PARAMS: &str = "Noise_XX_25519_ChaChaPoly_BLAKE2s";

/// Why keys or ciphertext were refused.
#[derive(Debug, thiserror::Error)]
pub enum CryptoError {
    /// A key file could not be read or written.
    #[error("key file {path}: {detail}")]
    KeyFile {
        /// The file.
        path: String,
        /// What went wrong.
        detail: String,
    },
    /// The Noise library refused (bad message, wrong key, ...).
    #[error("noise: {0}")]
    Noise(#[from] snow::Error),
    /// Authentication failed: wrong key, tampered or replayed.
    #[error("authentication failed")]
    Auth,
}

/// 32 random bytes from the operating system's CSPRNG (via `rand`'s thread RNG,
/// seeded from `getrandom`).
pub fn random_key() -> [u8; 32] {
    rand::random()
}

/// An X25519 key pair.
#[derive(Clone, PartialEq, Eq)]
pub struct KeyPair {
    /// Private half; never logged.
    pub private: [u8; 32],
    /// Public half; goes into the broker's access file.
    pub public: [u8; 32],
}

impl KeyPair {
    /// The stateless reset token of connection `conn` under this (broker's) key: any
    /// broker holding the key computes it, nobody else can (RFC 9000 §10.3).
    pub fn reset_token(&self, conn: u64) -> [u8; crate::udp::wire::RESET_TOKEN] {
        use hmac::Mac;
        let mut mac = <hmac::Hmac<sha2::Sha256> as Mac>::new_from_slice(&self.private)
            .expect("HMAC takes a key of any length");
        mac.update(b"muster stateless reset v1");
        mac.update(&conn.to_le_bytes());
        let full = mac.finalize().into_bytes();
        let mut token = [0u8; crate::udp::wire::RESET_TOKEN];
        token.copy_from_slice(&full[..crate::udp::wire::RESET_TOKEN]);
        token
    }
}

impl std::fmt::Debug for KeyPair {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "KeyPair {{ public: {} }}", hex::encode(self.public))
    }
}

fn params() -> snow::params::NoiseParams {
    NOISE_PARAMS
        .parse()
        .expect("NOISE_PARAMS is a valid Noise protocol name")
}

impl KeyPair {
    /// A fresh key pair.
    pub fn generate() -> Result<Self, CryptoError> {
        let kp = snow::Builder::new(params()).generate_keypair()?;
        Ok(KeyPair {
            private: to32(&kp.private).ok_or(CryptoError::Auth)?,
            public: to32(&kp.public).ok_or(CryptoError::Auth)?,
        })
    }

    /// The key file's text: `name`, then the private and public keys in hex.
    pub fn to_file_text(&self, name: &str) -> String {
        format!(
            "# muster key of {name}: keep private (chmod 600)\nname {name}\nprivate {}\npublic {}\n",
            hex::encode(self.private),
            hex::encode(self.public)
        )
    }

    /// Writes a key file readable only by its owner.
    pub fn write(&self, name: &str, path: &Path) -> Result<(), CryptoError> {
        write_secret(path, &self.to_file_text(name)).map_err(|e| CryptoError::KeyFile {
            path: path.display().to_string(),
            detail: e.to_string(),
        })
    }

    /// Reads a key file; returns the name in it and the key pair (checked to match).
    pub fn read(path: &Path) -> Result<(String, Self), CryptoError> {
        let bad = |detail: String| CryptoError::KeyFile {
            path: path.display().to_string(),
            detail,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        Self::parse(&text).map_err(bad)
    }

    /// Parses a key file's text.
    pub fn parse(text: &str) -> Result<(String, Self), String> {
        let (mut name, mut private, mut public) = (None, None, None);
        for line in text.lines().map(str::trim) {
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            match line.split_once(' ') {
                Some(("name", v)) => name = Some(v.trim().to_string()),
                Some(("private", v)) => private = Some(parse_key(v.trim())?),
                Some(("public", v)) => public = Some(parse_key(v.trim())?),
                _ => return Err(format!("unexpected line {line:?}")),
            }
        }
        let name = name.ok_or("no `name` line")?;
        let private = private.ok_or("no `private` line")?;
        let public = public.ok_or("no `public` line")?;
        // The public key must be the private key's: a wrong pair would fail every
        // handshake with an unhelpful error.
        let derived = x25519_public(&private)?;
        if derived != public {
            return Err("public key does not belong to the private key".into());
        }
        Ok((name, KeyPair { private, public }))
    }
}

/// The X25519 public key of `private`, computed by running a throwaway Noise handshake
/// half (snow exposes no scalar multiplication directly).
fn x25519_public(private: &[u8; 32]) -> Result<[u8; 32], String> {
    let mut ini = snow::Builder::new(params())
        .local_private_key(private)
        .and_then(|b| b.build_initiator())
        .map_err(|e| e.to_string())?;
    let mut resp = snow::Builder::new(params())
        .local_private_key(&[7u8; 32])
        .and_then(|b| b.build_responder())
        .map_err(|e| e.to_string())?;
    let mut buf = [0u8; 256];
    let mut out = [0u8; 256];
    let n = ini
        .write_message(&[], &mut buf)
        .map_err(|e| e.to_string())?;
    resp.read_message(&buf[..n], &mut out)
        .map_err(|e| e.to_string())?;
    let n = resp
        .write_message(&[], &mut buf)
        .map_err(|e| e.to_string())?;
    ini.read_message(&buf[..n], &mut out)
        .map_err(|e| e.to_string())?;
    let n = ini
        .write_message(&[], &mut buf)
        .map_err(|e| e.to_string())?;
    resp.read_message(&buf[..n], &mut out)
        .map_err(|e| e.to_string())?;
    resp.get_remote_static()
        .and_then(to32)
        .ok_or_else(|| "no remote static key".to_string())
}

/// Parses 64 hex digits into a key.
pub fn parse_key(s: &str) -> Result<[u8; 32], String> {
    let v = hex::decode(s).map_err(|e| format!("bad key {s:?}: {e}"))?;
    to32(&v).ok_or_else(|| format!("bad key {s:?}: need 64 hex digits"))
}

fn to32(b: &[u8]) -> Option<[u8; 32]> {
    b.try_into().ok()
}

/// A Noise XX initiator (the user's side).
pub fn initiator(me: &KeyPair) -> Result<snow::HandshakeState, CryptoError> {
    Ok(snow::Builder::new(params())
        .local_private_key(&me.private)?
        .build_initiator()?)
}

/// A Noise XX responder (the broker's side).
pub fn responder(me: &KeyPair) -> Result<snow::HandshakeState, CryptoError> {
    Ok(snow::Builder::new(params())
        .local_private_key(&me.private)?
        .build_responder()?)
}

/// Which nonces a receiver has seen: the highest, and a bitmap of the 1024 below it
/// (RFC 6479 style). Accepts reordering within the window, refuses replays and anything
/// older.
#[derive(Clone, Debug, Default)]
pub struct ReplayWindow {
    top: Option<u64>,
    bits: [u64; Self::WORDS],
}

impl ReplayWindow {
    const WORDS: usize = 16;
    /// Nonces more than this far below the highest seen are refused.
    pub const SIZE: u64 = (Self::WORDS as u64) * 64;

    /// Whether `n` would be accepted (not seen, not too old). Does not record it.
    pub fn check(&self, n: u64) -> bool {
        match self.top {
            None => true,
            Some(top) if n > top => true,
            Some(top) if top - n >= Self::SIZE => false,
            Some(_) => {
                let (w, b) = Self::slot(n);
                self.bits[w] & (1 << b) == 0
            }
        }
    }

    /// Records `n` (after its ciphertext authenticated). Returns `false` for a replay.
    pub fn accept(&mut self, n: u64) -> bool {
        if !self.check(n) {
            return false;
        }
        match self.top {
            Some(top) if n <= top => {}
            Some(top) => {
                // Clear the slots that slide into the window.
                let gap = n - top;
                if gap >= Self::SIZE {
                    self.bits = [0; Self::WORDS];
                } else {
                    for k in top + 1..=n {
                        let (w, b) = Self::slot(k);
                        self.bits[w] &= !(1 << b);
                    }
                }
                self.top = Some(n);
            }
            None => {
                self.top = Some(n);
            }
        }
        let (w, b) = Self::slot(n);
        self.bits[w] |= 1 << b;
        true
    }

    fn slot(n: u64) -> (usize, u32) {
        let i = n % Self::SIZE;
        ((i / 64) as usize, (i % 64) as u32)
    }
}

/// The user ↔ broker channel after the handshake: Noise transport messages with
/// explicit nonces (datagrams may be lost or reordered) and a replay window.
pub struct Channel {
    state: snow::StatelessTransportState,
    next_nonce: u64,
    window: ReplayWindow,
}

impl std::fmt::Debug for Channel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Channel {{ next_nonce: {} }}", self.next_nonce)
    }
}

impl Channel {
    /// Wraps a finished handshake.
    pub fn new(hs: snow::HandshakeState) -> Result<Self, CryptoError> {
        Ok(Channel {
            state: hs.into_stateless_transport_mode()?,
            next_nonce: 0,
            window: ReplayWindow::default(),
        })
    }

    /// The static key the other side proved in the handshake.
    pub fn remote_static(&self) -> Option<&[u8]> {
        self.state.get_remote_static()
    }

    /// Encrypts `plain`; returns the nonce used and the ciphertext.
    pub fn seal(&mut self, plain: &[u8]) -> Result<(u64, Vec<u8>), CryptoError> {
        let nonce = self.next_nonce;
        self.next_nonce += 1;
        let mut out = vec![0u8; plain.len() + super::wire::TAG];
        let n = self.state.write_message(nonce, plain, &mut out)?;
        out.truncate(n);
        Ok((nonce, out))
    }

    /// Decrypts and authenticates; refuses replays.
    pub fn open(&mut self, nonce: u64, sealed: &[u8]) -> Result<Vec<u8>, CryptoError> {
        if !self.window.check(nonce) || sealed.len() < super::wire::TAG {
            return Err(CryptoError::Auth);
        }
        let mut out = vec![0u8; sealed.len()];
        let n = self
            .state
            .read_message(nonce, sealed, &mut out)
            .map_err(|_| CryptoError::Auth)?;
        out.truncate(n);
        self.window.accept(nonce);
        Ok(out)
    }
}

/// Which end of a session channel sends: the top bit of the nonce, so the two
/// directions never reuse a nonce under the shared key.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// The user sends.
    User,
    /// The system sends.
    System,
}

impl Side {
    fn bit(self) -> u64 {
        match self {
            Side::User => 0,
            Side::System => 1 << 63,
        }
    }
}

/// One direction pair of a user ↔ system session under the key the broker issued:
/// ChaCha20-Poly1305, 96-bit nonce = the 64-bit counter (direction in its top bit),
/// the session id as associated data, and a replay window for what arrives.
pub struct SessionCipher {
    aead: ChaCha20Poly1305,
    me: Side,
    next: u64,
    window: ReplayWindow,
}

impl std::fmt::Debug for SessionCipher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "SessionCipher {{ me: {:?}, next: {} }}",
            self.me, self.next
        )
    }
}

impl SessionCipher {
    /// The cipher for side `me` of a session with `key`.
    pub fn new(key: &[u8; 32], me: Side) -> Self {
        SessionCipher {
            aead: ChaCha20Poly1305::new(Key::from_slice(key)),
            me,
            next: 0,
            window: ReplayWindow::default(),
        }
    }

    fn nonce(n: u64) -> Nonce {
        let mut b = [0u8; 12];
        b[4..].copy_from_slice(&n.to_le_bytes());
        *Nonce::from_slice(&b)
    }

    /// Encrypts `plain` for session `session`; returns the nonce and ciphertext.
    pub fn seal(&mut self, session: u64, plain: &[u8]) -> Result<(u64, Vec<u8>), CryptoError> {
        let n = self.next | self.me.bit();
        self.next += 1;
        let aad = session.to_le_bytes();
        let ct = self
            .aead
            .encrypt(
                &Self::nonce(n),
                AeadPayload {
                    msg: plain,
                    aad: &aad,
                },
            )
            .map_err(|_| CryptoError::Auth)?;
        Ok((n, ct))
    }

    /// Decrypts what the other side sent; refuses our own direction, tampering and replays.
    pub fn open(&mut self, session: u64, n: u64, sealed: &[u8]) -> Result<Vec<u8>, CryptoError> {
        if n & (1 << 63) == self.me.bit() || !self.window.check(n & !(1 << 63)) {
            return Err(CryptoError::Auth);
        }
        let aad = session.to_le_bytes();
        let plain = self
            .aead
            .decrypt(
                &Self::nonce(n),
                AeadPayload {
                    msg: sealed,
                    aad: &aad,
                },
            )
            .map_err(|_| CryptoError::Auth)?;
        self.window.accept(n & !(1 << 63));
        Ok(plain)
    }
}

/// Mints and checks stateless address-validation tokens: HMAC-SHA-256 under a secret
/// that lives only in the broker's memory, over the time, the client's address and its
/// handshake id. The broker keeps no state for a source until it returns a valid token.
#[derive(Clone)]
pub struct Cookies {
    secret: [u8; 32],
    /// How long a token stays valid, in seconds.
    pub lifetime_s: u64,
}

type HmacSha256 = Hmac<Sha256>;

/// Token length: 8-byte time stamp and a 16-byte truncated MAC.
pub const TOKEN_LEN: usize = 24;

impl Cookies {
    /// A fresh secret.
    pub fn new() -> Self {
        Self::with_secret(random_key())
    }

    /// Tokens under `secret` (drawn by the caller, e.g. from a seeded CSPRNG).
    pub fn with_secret(secret: [u8; 32]) -> Self {
        Cookies {
            secret,
            lifetime_s: 30,
        }
    }

    fn mac(&self, t: u64, addr: &SocketAddr, client: u64) -> HmacSha256 {
        let mut m = <HmacSha256 as Mac>::new_from_slice(&self.secret)
            .expect("HMAC takes keys of any length");
        m.update(&t.to_le_bytes());
        match addr {
            SocketAddr::V4(a) => m.update(&a.ip().octets()),
            SocketAddr::V6(a) => m.update(&a.ip().octets()),
        }
        m.update(&addr.port().to_le_bytes());
        m.update(&client.to_le_bytes());
        m
    }

    /// A token for `addr` and handshake `client` at time `now_s` (seconds).
    pub fn mint(&self, now_s: u64, addr: &SocketAddr, client: u64) -> [u8; TOKEN_LEN] {
        let mut t = [0u8; TOKEN_LEN];
        t[..8].copy_from_slice(&now_s.to_le_bytes());
        t[8..].copy_from_slice(&self.mac(now_s, addr, client).finalize().into_bytes()[..16]);
        t
    }

    /// Whether `token` was minted by us for this address and handshake, recently.
    pub fn check(&self, now_s: u64, token: &[u8], addr: &SocketAddr, client: u64) -> bool {
        if token.len() != TOKEN_LEN {
            return false;
        }
        let mut ts = [0u8; 8];
        ts.copy_from_slice(&token[..8]);
        let t = u64::from_le_bytes(ts);
        if t > now_s || now_s - t > self.lifetime_s {
            return false;
        }
        // Constant-time comparison through the MAC crate.
        self.mac(t, addr, client)
            .verify_truncated_left(&token[8..])
            .is_ok()
    }
}

impl Default for Cookies {
    fn default() -> Self {
        Self::new()
    }
}

/// Writes a secret (a key file, a web token) to a new file only its owner may read,
/// never over an existing one.
pub fn write_secret(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)?;
    f.write_all(text.as_bytes())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn handshake(user: &KeyPair, broker: &KeyPair) -> (Channel, Channel, [u8; 32]) {
        let mut i = initiator(user).unwrap();
        let mut r = responder(broker).unwrap();
        let (mut a, mut b) = ([0u8; 512], [0u8; 512]);
        let n = i.write_message(&[], &mut a).unwrap();
        r.read_message(&a[..n], &mut b).unwrap();
        let n = r.write_message(&[], &mut a).unwrap();
        i.read_message(&a[..n], &mut b).unwrap();
        let n = i.write_message(b"alice", &mut a).unwrap();
        let m = r.read_message(&a[..n], &mut b).unwrap();
        assert_eq!(&b[..m], b"alice");
        let seen = to32(r.get_remote_static().unwrap()).unwrap();
        (Channel::new(i).unwrap(), Channel::new(r).unwrap(), seen)
    }

    #[test]
    fn key_files_round_trip_and_mismatches_are_refused() {
        let k = KeyPair::generate().unwrap();
        let (name, back) = KeyPair::parse(&k.to_file_text("alice")).unwrap();
        assert_eq!((name.as_str(), &back), ("alice", &k));
        let other = KeyPair::generate().unwrap();
        let bad = format!(
            "name alice\nprivate {}\npublic {}\n",
            hex::encode(k.private),
            hex::encode(other.public)
        );
        assert!(KeyPair::parse(&bad)
            .unwrap_err()
            .contains("does not belong"));
        assert!(KeyPair::parse("name a\nprivate zz\n").is_err());
    }

    #[test]
    fn channel_authenticates_reorders_and_refuses_replays() {
        let (u, b) = (KeyPair::generate().unwrap(), KeyPair::generate().unwrap());
        let (mut cu, mut cb, seen) = handshake(&u, &b);
        assert_eq!(seen, u.public);
        let (n1, m1) = cu.seal(b"one").unwrap();
        let (n2, m2) = cu.seal(b"two").unwrap();
        assert_eq!(cb.open(n2, &m2).unwrap(), b"two");
        assert_eq!(cb.open(n1, &m1).unwrap(), b"one");
        assert!(cb.open(n1, &m1).is_err(), "replay refused");
        let mut bad = m2.clone();
        bad[0] ^= 1;
        assert!(cb.open(n2 + 1, &bad).is_err(), "tampering refused");
    }

    #[test]
    fn session_cipher_directions_and_replay() {
        let key = random_key();
        let mut user = SessionCipher::new(&key, Side::User);
        let mut sys = SessionCipher::new(&key, Side::System);
        let (n, ct) = user.seal(42, b"input").unwrap();
        assert!(user.open(42, n, &ct).is_err(), "own direction refused");
        assert!(sys.open(43, n, &ct).is_err(), "other session refused");
        assert_eq!(sys.open(42, n, &ct).unwrap(), b"input");
        assert!(sys.open(42, n, &ct).is_err(), "replay refused");
        let (n, ct) = sys.seal(42, b"update").unwrap();
        assert_eq!(user.open(42, n, &ct).unwrap(), b"update");
        let mut wrong = SessionCipher::new(&random_key(), Side::User);
        let (n, ct) = sys.seal(42, b"x").unwrap();
        assert!(wrong.open(42, n, &ct).is_err(), "wrong key refused");
    }

    #[test]
    fn replay_window_slides() {
        let mut w = ReplayWindow::default();
        assert!(w.accept(5));
        assert!(!w.accept(5));
        assert!(w.accept(3));
        assert!(w.accept(5000));
        assert!(!w.accept(5), "fell out of the window");
        assert!(w.accept(5000 - 100));
        assert!(!w.accept(5000 - 100));
        assert!(w.accept(5001));
    }

    #[test]
    fn cookies_bind_address_client_and_time() {
        let c = Cookies::new();
        let a: SocketAddr = "127.0.0.1:4000".parse().unwrap();
        let b: SocketAddr = "127.0.0.2:4000".parse().unwrap();
        let t = c.mint(100, &a, 9);
        assert!(c.check(100, &t, &a, 9));
        assert!(c.check(129, &t, &a, 9));
        assert!(!c.check(131, &t, &a, 9), "expired");
        assert!(!c.check(100, &t, &b, 9), "other address");
        assert!(!c.check(100, &t, &a, 8), "other handshake");
        assert!(!Cookies::new().check(100, &t, &a, 9), "other secret");
        assert!(!c.check(100, &t[..10], &a, 9));
    }
}
