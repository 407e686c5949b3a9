//! The datagram layout of the UDP path. Every datagram is a 3-byte header (magic,
//! version, kind) and a kind-specific body; [`Datagram::decode`] checks all of it and
//! never panics (a property test and a fuzz target feed it arbitrary bytes).
//!
//! | kind | body | sent by |
//! |---|---|---|
//! | `INITIAL` | client id, token, Noise message 1, zero padding to [`MIN_INITIAL`] bytes | user → broker |
//! | `RETRY` | client id, stateless address-validation token | broker → user |
//! | `HS_REPLY` | client id, connection id, Noise message 2 | broker → user |
//! | `HS_FINAL` | connection id, Noise message 3 (carries the user's name) | user → broker |
//! | `CHANNEL` | connection id, nonce, Noise transport ciphertext | both, user ↔ broker |
//! | `SESSION` | session id, nonce, AEAD ciphertext under the session key | both, user ↔ system |
//! | `RESET` | connection id, 16-byte stateless reset token | broker → user |

/// First byte of every muster datagram.
pub const UDP_MAGIC: u8 = 0x75; // 'u'
/// Version of the datagram layout; datagrams of other versions are dropped and counted.
pub const UDP_VERSION: u8 = 5;
/// No datagram carries more than this many bytes of UDP payload (issue 3, and the
/// smallest path MTU QUIC assumes).
pub const MAX_DATAGRAM: usize = 1200;
/// An `INITIAL` is padded to this size, so that the broker's answer to an address it
/// has not validated (a `RETRY`) is far below 3× what it received (RFC 9000 §8.1).
pub const MIN_INITIAL: usize = 1200;
/// Longest address-validation token.
pub const MAX_TOKEN: usize = 64;
/// Longest handshake message carried.
pub const MAX_NOISE: usize = 512;

/// Datagram kinds (byte 2).
pub mod kind {
    /// Client's first datagram (with or without a token).
    pub const INITIAL: u8 = 1;
    /// Stateless retry carrying a token.
    pub const RETRY: u8 = 2;
    /// Broker's handshake reply.
    pub const HS_REPLY: u8 = 3;
    /// Client's last handshake message.
    pub const HS_FINAL: u8 = 4;
    /// Encrypted user ↔ broker message.
    pub const CHANNEL: u8 = 5;
    /// Encrypted user ↔ system message.
    pub const SESSION: u8 = 6;
    /// Stateless reset: a broker that does not know the connection (a standby took
    /// over, or the broker restarted with the same key) tells the user to shake hands
    /// again (RFC 9000 §10.3).
    pub const RESET: u8 = 7;
}

/// Length of a stateless reset token.
pub const RESET_TOKEN: usize = 16;

/// Why a datagram was dropped. Each has its own counter.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// Shorter than its header or its fixed fields.
    #[error("truncated datagram ({0} bytes)")]
    Truncated(usize),
    /// Not a muster datagram.
    #[error("bad magic {0:#04x}")]
    BadMagic(u8),
    /// Another layout version.
    #[error("datagram version {0}, this build speaks {UDP_VERSION}")]
    WrongVersion(u8),
    /// Unknown kind byte.
    #[error("unknown datagram kind {0}")]
    UnknownKind(u8),
    /// Larger than [`MAX_DATAGRAM`], or a field longer than its limit.
    #[error("oversized datagram or field ({0} bytes)")]
    Oversized(usize),
    /// An `INITIAL` below [`MIN_INITIAL`] bytes (not padded: refused, so we never amplify).
    #[error("unpadded initial ({0} bytes)")]
    Unpadded(usize),
    /// Bytes left after the fields of a fixed-layout kind.
    #[error("{0} trailing bytes")]
    Trailing(usize),
}

/// One decoded datagram; byte fields borrow from the received buffer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Datagram<'a> {
    /// See [`kind::INITIAL`].
    Initial {
        /// Random per handshake attempt, echoed by the broker.
        client: u64,
        /// Empty on the first try; the `RETRY` token after.
        token: &'a [u8],
        /// Noise message 1.
        noise: &'a [u8],
    },
    /// See [`kind::RETRY`].
    Retry {
        /// Echo of the client id.
        client: u64,
        /// Token to send back.
        token: &'a [u8],
    },
    /// See [`kind::HS_REPLY`].
    HsReply {
        /// Echo of the client id.
        client: u64,
        /// Connection id the broker assigned.
        conn: u64,
        /// Noise message 2.
        noise: &'a [u8],
    },
    /// See [`kind::HS_FINAL`].
    HsFinal {
        /// Connection id.
        conn: u64,
        /// Noise message 3.
        noise: &'a [u8],
    },
    /// See [`kind::CHANNEL`].
    Channel {
        /// Connection id.
        conn: u64,
        /// Sender's nonce (counter), authenticated by the AEAD.
        nonce: u64,
        /// Ciphertext and tag.
        sealed: &'a [u8],
    },
    /// See [`kind::SESSION`].
    Session {
        /// Session id.
        session: u64,
        /// Sender's nonce (counter; the top bit says the direction).
        nonce: u64,
        /// Ciphertext and tag.
        sealed: &'a [u8],
    },
    /// See [`kind::RESET`].
    Reset {
        /// The connection the broker does not know.
        conn: u64,
        /// The token the user got for it in the handshake.
        token: [u8; RESET_TOKEN],
    },
}

struct Reader<'a> {
    buf: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn u8(&mut self) -> Result<u8, WireError> {
        let b = *self
            .buf
            .get(self.at)
            .ok_or(WireError::Truncated(self.buf.len()))?;
        self.at += 1;
        Ok(b)
    }
    fn u16(&mut self) -> Result<u16, WireError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], WireError> {
        let s = self.bytes(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }
    fn bytes(&mut self, n: usize) -> Result<&'a [u8], WireError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|e| *e <= self.buf.len())
            .ok_or(WireError::Truncated(self.buf.len()))?;
        let s = &self.buf[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn rest(&mut self) -> &'a [u8] {
        let s = &self.buf[self.at..];
        self.at = self.buf.len();
        s
    }
    fn done(&self) -> Result<(), WireError> {
        match self.buf.len() - self.at {
            0 => Ok(()),
            n => Err(WireError::Trailing(n)),
        }
    }
}

fn limited(len: usize, max: usize) -> Result<usize, WireError> {
    if len > max {
        Err(WireError::Oversized(len))
    } else {
        Ok(len)
    }
}

impl<'a> Datagram<'a> {
    /// Decodes and checks one received datagram.
    pub fn decode(buf: &'a [u8]) -> Result<Self, WireError> {
        if buf.len() > MAX_DATAGRAM {
            return Err(WireError::Oversized(buf.len()));
        }
        if buf.len() < 3 {
            return Err(WireError::Truncated(buf.len()));
        }
        if buf[0] != UDP_MAGIC {
            return Err(WireError::BadMagic(buf[0]));
        }
        if buf[1] != UDP_VERSION {
            return Err(WireError::WrongVersion(buf[1]));
        }
        let mut r = Reader { buf, at: 3 };
        let d = match buf[2] {
            kind::INITIAL => {
                if buf.len() < MIN_INITIAL {
                    return Err(WireError::Unpadded(buf.len()));
                }
                let client = r.u64()?;
                let tlen = limited(r.u8()? as usize, MAX_TOKEN)?;
                let token = r.bytes(tlen)?;
                let nlen = limited(r.u16()? as usize, MAX_NOISE)?;
                let noise = r.bytes(nlen)?;
                if r.rest().iter().any(|b| *b != 0) {
                    return Err(WireError::Trailing(buf.len()));
                }
                Datagram::Initial {
                    client,
                    token,
                    noise,
                }
            }
            kind::RETRY => {
                let client = r.u64()?;
                let tlen = limited(r.u8()? as usize, MAX_TOKEN)?;
                let token = r.bytes(tlen)?;
                r.done()?;
                Datagram::Retry { client, token }
            }
            kind::HS_REPLY => {
                let client = r.u64()?;
                let conn = r.u64()?;
                let nlen = limited(r.u16()? as usize, MAX_NOISE)?;
                let noise = r.bytes(nlen)?;
                r.done()?;
                Datagram::HsReply {
                    client,
                    conn,
                    noise,
                }
            }
            kind::HS_FINAL => {
                let conn = r.u64()?;
                let nlen = limited(r.u16()? as usize, MAX_NOISE)?;
                let noise = r.bytes(nlen)?;
                r.done()?;
                Datagram::HsFinal { conn, noise }
            }
            kind::CHANNEL => Datagram::Channel {
                conn: r.u64()?,
                nonce: r.u64()?,
                sealed: r.rest(),
            },
            kind::SESSION => Datagram::Session {
                session: r.u64()?,
                nonce: r.u64()?,
                sealed: r.rest(),
            },
            kind::RESET => {
                let conn = r.u64()?;
                let mut token = [0u8; RESET_TOKEN];
                token.copy_from_slice(r.bytes(RESET_TOKEN)?);
                r.done()?;
                Datagram::Reset { conn, token }
            }
            k => return Err(WireError::UnknownKind(k)),
        };
        Ok(d)
    }

    /// Encodes the datagram (an `INITIAL` padded to [`MIN_INITIAL`]); fails if it would
    /// exceed [`MAX_DATAGRAM`] or a field its limit.
    pub fn encode(&self) -> Result<Vec<u8>, WireError> {
        let mut out = Vec::with_capacity(64);
        let put_len8 = |out: &mut Vec<u8>, b: &[u8], max: usize| -> Result<(), WireError> {
            limited(b.len(), max)?;
            out.push(b.len() as u8);
            out.extend_from_slice(b);
            Ok(())
        };
        let put_len16 = |out: &mut Vec<u8>, b: &[u8], max: usize| -> Result<(), WireError> {
            limited(b.len(), max)?;
            out.extend_from_slice(&(b.len() as u16).to_le_bytes());
            out.extend_from_slice(b);
            Ok(())
        };
        out.extend_from_slice(&[UDP_MAGIC, UDP_VERSION, self.kind()]);
        match self {
            Datagram::Initial {
                client,
                token,
                noise,
            } => {
                out.extend_from_slice(&client.to_le_bytes());
                put_len8(&mut out, token, MAX_TOKEN)?;
                put_len16(&mut out, noise, MAX_NOISE)?;
                if out.len() < MIN_INITIAL {
                    out.resize(MIN_INITIAL, 0);
                }
            }
            Datagram::Retry { client, token } => {
                out.extend_from_slice(&client.to_le_bytes());
                put_len8(&mut out, token, MAX_TOKEN)?;
            }
            Datagram::HsReply {
                client,
                conn,
                noise,
            } => {
                out.extend_from_slice(&client.to_le_bytes());
                out.extend_from_slice(&conn.to_le_bytes());
                put_len16(&mut out, noise, MAX_NOISE)?;
            }
            Datagram::HsFinal { conn, noise } => {
                out.extend_from_slice(&conn.to_le_bytes());
                put_len16(&mut out, noise, MAX_NOISE)?;
            }
            Datagram::Channel {
                conn: id,
                nonce,
                sealed,
            }
            | Datagram::Session {
                session: id,
                nonce,
                sealed,
            } => {
                out.extend_from_slice(&id.to_le_bytes());
                out.extend_from_slice(&nonce.to_le_bytes());
                out.extend_from_slice(sealed);
            }
            Datagram::Reset { conn, token } => {
                out.extend_from_slice(&conn.to_le_bytes());
                out.extend_from_slice(token);
            }
        }
        if out.len() > MAX_DATAGRAM {
            return Err(WireError::Oversized(out.len()));
        }
        Ok(out)
    }

    /// The kind byte.
    pub fn kind(&self) -> u8 {
        match self {
            Datagram::Initial { .. } => kind::INITIAL,
            Datagram::Retry { .. } => kind::RETRY,
            Datagram::HsReply { .. } => kind::HS_REPLY,
            Datagram::HsFinal { .. } => kind::HS_FINAL,
            Datagram::Channel { .. } => kind::CHANNEL,
            Datagram::Session { .. } => kind::SESSION,
            Datagram::Reset { .. } => kind::RESET,
        }
    }
}

/// Bytes of header in front of the ciphertext of `CHANNEL` and `SESSION` datagrams.
pub const SEALED_HEADER: usize = 3 + 8 + 8;
/// AEAD tag length.
pub const TAG: usize = 16;
/// Largest plaintext that fits a `CHANNEL`/`SESSION` datagram.
pub const MAX_PLAINTEXT: usize = MAX_DATAGRAM - SEALED_HEADER - TAG;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn round_trips_every_kind() {
        let all = [
            Datagram::Initial {
                client: 7,
                token: b"tok",
                noise: &[1; 32],
            },
            Datagram::Retry {
                client: 7,
                token: &[9; 24],
            },
            Datagram::HsReply {
                client: 7,
                conn: 99,
                noise: &[2; 96],
            },
            Datagram::HsFinal {
                conn: 99,
                noise: &[3; 80],
            },
            Datagram::Channel {
                conn: 99,
                nonce: 5,
                sealed: &[4; 40],
            },
            Datagram::Session {
                session: 1 << 40,
                nonce: 1 << 63,
                sealed: &[5; 17],
            },
            Datagram::Reset {
                conn: 77,
                token: [6; RESET_TOKEN],
            },
        ];
        for d in all {
            let bytes = d.encode().unwrap();
            assert!(bytes.len() <= MAX_DATAGRAM);
            assert_eq!(Datagram::decode(&bytes).unwrap(), d);
        }
    }

    #[test]
    fn initial_is_padded_and_short_initials_refused() {
        let d = Datagram::Initial {
            client: 1,
            token: b"",
            noise: &[1; 32],
        };
        let bytes = d.encode().unwrap();
        assert_eq!(bytes.len(), MIN_INITIAL);
        assert_eq!(
            Datagram::decode(&bytes[..600]),
            Err(WireError::Unpadded(600))
        );
        let mut junk = bytes.clone();
        junk[1199] = 1;
        assert!(matches!(
            Datagram::decode(&junk),
            Err(WireError::Trailing(_))
        ));
    }

    #[test]
    fn refuses_bad_headers_and_limits() {
        assert_eq!(Datagram::decode(&[]), Err(WireError::Truncated(0)));
        assert_eq!(Datagram::decode(&[0, 1, 2]), Err(WireError::BadMagic(0)));
        assert_eq!(
            Datagram::decode(&[UDP_MAGIC, 9, 1]),
            Err(WireError::WrongVersion(9))
        );
        assert_eq!(
            Datagram::decode(&[UDP_MAGIC, UDP_VERSION, 77]),
            Err(WireError::UnknownKind(77))
        );
        assert_eq!(
            Datagram::decode(&vec![UDP_MAGIC; MAX_DATAGRAM + 1]),
            Err(WireError::Oversized(MAX_DATAGRAM + 1))
        );
        let d = Datagram::Channel {
            conn: 1,
            nonce: 1,
            sealed: &[0; MAX_DATAGRAM],
        };
        assert!(matches!(d.encode(), Err(WireError::Oversized(_))));
        let retry = Datagram::Retry {
            client: 1,
            token: &[0; 8],
        }
        .encode()
        .unwrap();
        assert_eq!(
            Datagram::decode(&retry[..retry.len() - 1]),
            Err(WireError::Truncated(retry.len() - 1))
        );
    }

    proptest! {
        #[test]
        fn decode_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..1300)) {
            let _ = Datagram::decode(&bytes);
        }

        #[test]
        fn decode_never_panics_with_a_valid_header(k in 0u8..8, bytes in proptest::collection::vec(any::<u8>(), 0..1300)) {
            let mut b = vec![UDP_MAGIC, UDP_VERSION, k];
            b.extend(bytes);
            if let Ok(d) = Datagram::decode(&b) {
                // Whatever decodes re-encodes to something that decodes the same.
                let again = d.encode().unwrap();
                prop_assert_eq!(Datagram::decode(&again).unwrap(), d);
            }
        }
    }
}
