//! What travels inside the encrypted channels, and the list split into datagrams.

use super::wire::MAX_PLAINTEXT;
use crate::protocol::{ToBroker, ToSystem, ToUser};
use crate::snapshot::ServiceView;
use crate::types::{ServiceId, ServiceKind, SessionId, UserId};
use serde::{Deserialize, Serialize};

/// The payload of Noise message 3: who the user says it is. The broker checks the
/// static key the handshake proved against the access file's key for `name`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hs3 {
    /// User name in the access file.
    pub name: String,
    /// Chosen by the client once per process: the user id is `name.suffix`, kept across
    /// reconnections so sessions and links stay the user's.
    pub suffix: String,
}

/// User → broker, inside a `CHANNEL` datagram.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Up {
    /// A user message: `Hello`, `Request`, `Cancel`, `LinkOpened`, `LinkClosed` or
    /// `Goodbye`. The broker replaces its user and pid fields with what it authenticated.
    Msg(ToBroker),
    /// Send me the services of the list that `filter` lets through, from the
    /// `offset`th of them, at most `limit` (all chunks of the current generation).
    /// The whole list: no filter, from 0, `u32::MAX`.
    List {
        /// The ask's number, echoed in each chunk of the answer (an answer to an earlier
        /// ask, late or repeated, is not taken for this one's).
        ask: u32,
        /// Which services.
        filter: crate::snapshot::ListFilter,
        /// How many of them to skip.
        offset: u32,
        /// Most to send.
        limit: u32,
    },
    /// Keepalive; answered by [`Down::Pong`].
    Ping {
        /// Echoed.
        nonce: u64,
    },
    /// Answer to [`Down::PathChallenge`], from the address it reached.
    PathResponse {
        /// The challenge's token.
        token: u64,
    },
}

/// Broker → user, inside a `CHANNEL` datagram.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Down {
    /// The hello was accepted; this is the user's id in the federation.
    Welcome {
        /// The id the broker gave this connection (`name.suffix`).
        user: UserId,
        /// Broker run.
        epoch: u64,
    },
    /// A user message (`Queued`, `Refused`).
    Msg(ToUser),
    /// The request was granted; session data comes from the system at `system_addr`,
    /// sealed with `key`.
    Granted {
        /// Request number.
        req: u64,
        /// The session.
        session: SessionId,
        /// Service.
        service: ServiceId,
        /// Data or command.
        kind: ServiceKind,
        /// Payload type.
        payload: String,
        /// Where the system's UDP endpoint listens.
        system_addr: String,
        /// The session key (the channel carrying it is encrypted).
        key: [u8; 32],
    },
    /// One piece of the service list.
    ListChunk {
        /// Broker run.
        epoch: u64,
        /// List generation.
        generation: u64,
        /// Index of this chunk, from 0.
        index: u16,
        /// Number of chunks.
        total: u16,
        /// The ask this answers ([`Up::List`]'s).
        ask: u32,
        /// How many services of the whole list the asked filter lets through (the
        /// chunks hold those from the asked offset, at most the asked limit).
        matching: u32,
        /// The services in it.
        entries: Vec<ServiceView>,
    },
    /// The list changed (rate-limited like the local bell).
    ListChanged {
        /// New generation.
        generation: u64,
    },
    /// Answer to [`Up::Ping`], with the list generation so a lost `ListChanged` is noticed.
    Pong {
        /// Echo.
        nonce: u64,
        /// Current list generation.
        generation: u64,
    },
    /// An authenticated datagram came from a new address: prove you are there (RFC 9000
    /// §8.2). Until the answer comes back from it, nothing else is sent there.
    PathChallenge {
        /// Echo this in [`Up::PathResponse`].
        token: u64,
    },
    /// One piece of the answer to an operator's action (`ToBroker::Operate`): the
    /// answer's frame (`muster_shared::protocol::encode` of
    /// `Result<Option<Box<BrokerStatus>>, String>`), cut to fit datagrams. An action
    /// sent again is answered again, whole, from the broker's memory.
    OperatedChunk {
        /// The action's number.
        id: u64,
        /// Index of this piece, from 0.
        index: u16,
        /// Number of pieces.
        total: u16,
        /// The bytes.
        bytes: Vec<u8>,
    },
    /// A record of the broker's event feed (its JSON, as the shared-memory feed has
    /// it), for an operator that has acted; best effort: a lost one shows as a gap in
    /// the records' `seq`.
    Event(String),
}

/// Bytes of an operator's answer in one [`Down::OperatedChunk`].
pub const OPERATED_CHUNK: usize = MAX_PLAINTEXT - 64;

/// User → system, inside a `SESSION` datagram.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SessionUp {
    /// `Input` or `End` (the system checks the session and replaces the user field).
    Msg(ToSystem),
    /// The user is alive; answered by [`SessionDown::Alive`].
    Keepalive,
    /// Answer to [`SessionDown::PathChallenge`].
    PathResponse {
        /// The challenge's token.
        token: u64,
    },
}

/// System → user, inside a `SESSION` datagram.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SessionDown {
    /// `Update`, `Status` or `Ended`.
    Msg(ToUser),
    /// The system is alive.
    Alive,
    /// A datagram of this session came from a new address: prove you are there.
    PathChallenge {
        /// Echo this in [`SessionUp::PathResponse`].
        token: u64,
    },
}

/// Why a channel message could not be encoded or decoded.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum MsgError {
    /// Too large for one datagram.
    #[error("message of {0} bytes does not fit a datagram ({MAX_PLAINTEXT} bytes)")]
    TooLarge(usize),
    /// Bytes that are no message.
    #[error("malformed message: {0}")]
    Malformed(String),
}

/// Encodes a channel message; fails if it would not fit one datagram.
pub fn to_bytes<T: Serialize>(m: &T) -> Result<Vec<u8>, MsgError> {
    let v = postcard::to_stdvec(m).map_err(|e| MsgError::Malformed(e.to_string()))?;
    if v.len() > MAX_PLAINTEXT {
        return Err(MsgError::TooLarge(v.len()));
    }
    Ok(v)
}

/// Decodes a channel message; trailing bytes are an error.
pub fn from_bytes<'de, T: Deserialize<'de>>(b: &'de [u8]) -> Result<T, MsgError> {
    let (m, rest) = postcard::take_from_bytes(b).map_err(|e| MsgError::Malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(MsgError::Malformed(format!(
            "{} trailing bytes",
            rest.len()
        )));
    }
    Ok(m)
}

/// Encodes `m`, seals it on the user ↔ broker channel and frames it as a `CHANNEL`
/// datagram of connection `conn`.
pub fn seal_channel<T: Serialize>(
    chan: &mut super::crypto::Channel,
    conn: u64,
    m: &T,
) -> Result<Vec<u8>, MsgError> {
    let plain = to_bytes(m)?;
    let (nonce, sealed) = chan
        .seal(&plain)
        .map_err(|e| MsgError::Malformed(e.to_string()))?;
    super::wire::Datagram::Channel {
        conn,
        nonce,
        sealed: &sealed,
    }
    .encode()
    .map_err(|e| MsgError::Malformed(e.to_string()))
}

/// Encodes `m`, seals it under a session's key and frames it as a `SESSION` datagram.
pub fn seal_session<T: Serialize>(
    cipher: &mut super::crypto::SessionCipher,
    session: u64,
    m: &T,
) -> Result<Vec<u8>, MsgError> {
    let plain = to_bytes(m)?;
    let (nonce, sealed) = cipher
        .seal(session, &plain)
        .map_err(|e| MsgError::Malformed(e.to_string()))?;
    super::wire::Datagram::Session {
        session,
        nonce,
        sealed: &sealed,
    }
    .encode()
    .map_err(|e| MsgError::Malformed(e.to_string()))
}

/// [`Down::ListChunk`] over borrowed entries, as [`chunk_list`] makes them: encodes to
/// the same bytes (the variant's index, then its fields in order), so a list answer
/// serializes the broker's own views instead of copies of them.
#[derive(Debug, PartialEq)]
pub struct ListChunkRef<'a> {
    /// Broker run.
    pub epoch: u64,
    /// List generation.
    pub generation: u64,
    /// Index of this chunk, from 0.
    pub index: u16,
    /// Number of chunks.
    pub total: u16,
    /// The ask this answers.
    pub ask: u32,
    /// How many services the asked filter lets through.
    pub matching: u32,
    /// The services in it.
    pub entries: Vec<&'a ServiceView>,
}

/// [`Down::ListChunk`]'s place among `Down`'s variants (its serialized tag); a test
/// holds it to the enum.
const LIST_CHUNK_VARIANT: u32 = 3;

impl Serialize for ListChunkRef<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStructVariant;
        let mut v = s.serialize_struct_variant("Down", LIST_CHUNK_VARIANT, "ListChunk", 7)?;
        v.serialize_field("epoch", &self.epoch)?;
        v.serialize_field("generation", &self.generation)?;
        v.serialize_field("index", &self.index)?;
        v.serialize_field("total", &self.total)?;
        v.serialize_field("ask", &self.ask)?;
        v.serialize_field("matching", &self.matching)?;
        v.serialize_field("entries", &self.entries)?;
        v.end()
    }
}

/// Splits a list into `ListChunk`s that each fit one datagram.
pub fn chunk_list<'a>(
    epoch: u64,
    generation: u64,
    (ask, matching): (u32, u32),
    views: Vec<&'a ServiceView>,
) -> Vec<ListChunkRef<'a>> {
    // Room for the chunk's own fields and postcard's length prefixes.
    const BUDGET: usize = MAX_PLAINTEXT - 40;
    let mut groups: Vec<Vec<&ServiceView>> = vec![Vec::new()];
    let mut used = 0;
    for v in views {
        let size = postcard::experimental::serialized_size(&v).unwrap_or(BUDGET);
        if used + size > BUDGET && !groups.last().is_some_and(Vec::is_empty) {
            groups.push(Vec::new());
            used = 0;
        }
        used += size;
        groups.last_mut().expect("never empty").push(v);
    }
    // A chunk's number is 16 bits: a longer answer is cut there (about half a million
    // services), and `matching` still says how many there are, for pages.
    groups.truncate(usize::from(u16::MAX));
    let total = groups.len() as u16;
    groups
        .into_iter()
        .enumerate()
        .map(|(i, entries)| ListChunkRef {
            epoch,
            generation,
            index: i as u16,
            total,
            ask,
            matching,
            entries,
        })
        .collect()
}

/// An operator's answer: done (with the status, for a status read), or why not.
pub type OperatedResult = Result<Option<Box<crate::protocol::BrokerStatus>>, String>;

/// Cuts the answer to operator action `id` into [`Down::OperatedChunk`]s; `None` if it
/// cannot be encoded (larger than a frame: the broker cuts a status to fit first).
pub fn chunk_operated(id: u64, result: &OperatedResult) -> Option<Vec<Down>> {
    let frame = crate::protocol::encode(result).ok()?;
    let pieces: Vec<&[u8]> = frame.chunks(OPERATED_CHUNK).collect();
    let total = u16::try_from(pieces.len()).ok()?;
    Some(
        pieces
            .into_iter()
            .enumerate()
            .map(|(i, b)| Down::OperatedChunk {
                id,
                index: i as u16,
                total,
                bytes: b.to_vec(),
            })
            .collect(),
    )
}

/// Puts an operator's answer together from its [`Down::OperatedChunk`]s, which may come
/// in any order, more than once, or (after the action was sent again) anew.
#[derive(Debug, Default)]
pub struct OperatedAssembly {
    total: u16,
    pieces: std::collections::BTreeMap<u16, Vec<u8>>,
}

impl OperatedAssembly {
    /// Takes one piece; the answer once every piece is in (an answer that does not
    /// decode is an error naming why).
    pub fn add(&mut self, index: u16, total: u16, bytes: Vec<u8>) -> Option<OperatedResult> {
        if total == 0 || index >= total {
            return None;
        }
        if total != self.total {
            self.total = total;
            self.pieces.clear();
        }
        self.pieces.insert(index, bytes);
        if self.pieces.len() < usize::from(total) {
            return None;
        }
        let frame: Vec<u8> = self.pieces.values().flatten().copied().collect();
        self.pieces.clear();
        Some(
            crate::protocol::decode::<OperatedResult>(&frame)
                .unwrap_or_else(|e| Err(format!("the broker's answer did not decode: {e}"))),
        )
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn an_operators_answer_goes_in_pieces_and_comes_back_whole() {
        use crate::protocol::{BrokerStatus, UserStatus};
        let status = BrokerStatus {
            epoch: 7,
            users: (0..150)
                .map(|i| UserStatus {
                    user: UserId(format!("user-{i}-with-a-longish-name")),
                    pid: i,
                    links: Vec::new(),
                })
                .collect(),
            users_total: 150,
            ..BrokerStatus::default()
        };
        let result: OperatedResult = Ok(Some(Box::new(status)));
        let chunks = chunk_operated(9, &result).unwrap();
        assert!(chunks.len() >= 3, "{}", chunks.len());
        for c in &chunks {
            let sealed = crate::udp::wire::MAX_PLAINTEXT;
            assert!(postcard::to_stdvec(c).unwrap().len() <= sealed);
        }
        let mut parts: Vec<(u16, u16, Vec<u8>)> = chunks
            .into_iter()
            .map(|c| match c {
                Down::OperatedChunk {
                    id: 9,
                    index,
                    total,
                    bytes,
                } => (index, total, bytes),
                other => panic!("{other:?}"),
            })
            .collect();
        // Backwards, the last one twice: whole only at the end.
        parts.reverse();
        let mut a = OperatedAssembly::default();
        let last = parts.pop().unwrap();
        assert!(a.add(parts[0].0, parts[0].1, parts[0].2.clone()).is_none());
        for (i, t, b) in parts {
            assert!(a.add(i, t, b).is_none());
        }
        assert_eq!(a.add(last.0, last.1, last.2), Some(result));
        // Nonsense is no answer, and garbage that claims to be whole is an error.
        let mut a = OperatedAssembly::default();
        assert!(a.add(3, 2, vec![1]).is_none());
        assert!(matches!(a.add(0, 1, vec![1, 2, 3]), Some(Err(e)) if e.contains("did not decode")));
    }

    fn view(i: usize) -> ServiceView {
        ServiceView {
            id: format!("system{i:02}/service-with-a-long-name-{i:03}"),
            system: format!("system{i:02}"),
            name: format!("service-with-a-long-name-{i:03}"),
            description: "d".repeat(95),
            kind: "data".into(),
            queue: i.is_multiple_of(2),
            quota: 10,
            in_use: 1,
            queued: 0,
            links: 0,
            withdrawn: false,
            // The longest payload type an open type may have.
            payload: format!("pkg_{i:03}/msg/{}", "T".repeat(52)),
            encoding: "cdr".into(),
            host: String::new(),
            remote: false,
        }
    }

    #[test]
    fn lists_split_into_datagrams_and_reassemble_in_order() {
        let views: Vec<ServiceView> = (0..256).map(view).collect();
        let chunks = chunk_list(1, 9, (1, 256), views.iter().collect());
        assert!(chunks.len() > 10, "256 long entries need many datagrams");
        let mut back = Vec::new();
        for (i, c) in chunks.iter().enumerate() {
            let bytes = to_bytes(c).unwrap();
            assert!(bytes.len() <= MAX_PLAINTEXT);
            match from_bytes::<Down>(&bytes).unwrap() {
                Down::ListChunk {
                    index,
                    total,
                    generation,
                    entries,
                    ..
                } => {
                    assert_eq!(
                        (index as usize, total as usize, generation),
                        (i, chunks.len(), 9)
                    );
                    back.extend(entries);
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(back, views);
        // The borrowed chunk is the owned one, byte for byte.
        let c = &chunks[1];
        let owned = Down::ListChunk {
            epoch: c.epoch,
            generation: c.generation,
            index: c.index,
            total: c.total,
            ask: c.ask,
            matching: c.matching,
            entries: c.entries.iter().map(|v| (*v).clone()).collect(),
        };
        assert_eq!(to_bytes(c).unwrap(), to_bytes(&owned).unwrap());
        assert_eq!(
            chunk_list(1, 1, (1, 0), Vec::new()).len(),
            1,
            "an empty list is one empty chunk"
        );
    }

    #[test]
    fn oversized_messages_are_refused() {
        let m = SessionDown::Msg(ToUser::Update {
            session: SessionId(1),
            seq: 1,
            sent_ns: 0,
            payload: crate::types::Payload::Text("x".repeat(2000)),
        });
        assert!(matches!(to_bytes(&m), Err(MsgError::TooLarge(_))));
    }

    proptest! {
        #[test]
        fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..1200)) {
            let _ = from_bytes::<Up>(&bytes);
            let _ = from_bytes::<Down>(&bytes);
            let _ = from_bytes::<SessionUp>(&bytes);
            let _ = from_bytes::<SessionDown>(&bytes);
        }
    }
}
