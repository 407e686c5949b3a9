//! Replication from a primary broker to its standbys: the records, in rkyv's archived
//! form, and the two ends, with no I/O.
//!
//! The core is deterministic: the same inputs in the same order give the same state. A
//! primary therefore ships its state once ([`Record::Image`], when a standby asks) and
//! then every input it applies ([`Record::Op`], numbered), and a standby applies them to
//! its own copy. Records are archived with rkyv, so a standby checks and reads each one
//! in place in the shared-memory sample it arrives in; only an input's message is
//! turned back into an owned value, to hand to the core.
//!
//! The primary publishes an op's record before it sends what the op made the core say
//! (write-ahead): whatever a peer heard from the primary, a standby will know of.

use crate::core::{Broker, Op};
use rkyv::rancor;
use rkyv::util::AlignedVec;
use std::time::Duration;

/// One replication record. Only its archived form is ever built (from a borrowing twin,
/// without copying the state) and read.
#[allow(clippy::large_enum_variant)]
#[derive(rkyv::Archive, rkyv::Serialize, rkyv::Deserialize, Debug)]
pub enum Record {
    /// The primary's whole state after op `seq` (0: none yet): a standby starts here.
    Image(u64, Broker),
    /// Op number `seq`, applied at `now` on the host's monotonic clock.
    Op(u64, Duration, Op),
    /// The primary is alive; its last op is `seq`. A standby that has not seen `seq` lost
    /// records and asks for a new image.
    Heartbeat(u64),
    /// The primary is stopping on purpose after op `seq`: a standby takes over at once.
    SteppingDown(u64),
}

/// Why a record could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReplicaError {
    /// The bytes are not a valid archived record (rkyv's check failed).
    #[error("malformed replication record: {0}")]
    Malformed(String),
}

/// The primary's end: numbers the journal and archives records.
#[derive(Debug, Default)]
pub struct Leader {
    seq: u64,
}

impl Leader {
    /// Starts numbering after op `seq` (a new primary continues its predecessor's count).
    pub fn after(seq: u64) -> Self {
        Leader { seq }
    }

    /// The number of the last op archived.
    pub fn seq(&self) -> u64 {
        self.seq
    }

    /// Archives the core's journal since the last call, one record per op.
    pub fn ops(&mut self, core: &mut Broker) -> Vec<AlignedVec> {
        core.take_journal()
            .into_iter()
            .map(|(now, op)| {
                self.seq += 1;
                archive(&RecordRef::Op(self.seq, now, &op))
            })
            .collect()
    }

    /// Archives the core's whole state as of the last op. Take the journal first
    /// ([`Leader::ops`]): the image must not run ahead of the numbered ops.
    pub fn image(&self, core: &Broker) -> AlignedVec {
        archive(&RecordRef::Image(self.seq, core))
    }

    /// Archives a heartbeat.
    pub fn heartbeat(&self) -> AlignedVec {
        archive(&RecordRef::Heartbeat(self.seq))
    }

    /// Archives the primary's notice that it is stopping.
    pub fn stepping_down(&self) -> AlignedVec {
        archive(&RecordRef::SteppingDown(self.seq))
    }
}

/// What a standby did with a record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// The record moved the copy forward (an image or the next op).
    Applied,
    /// Nothing to do (an old or repeated record, a heartbeat in step, or an op before
    /// the first image).
    Ignored,
    /// Records were lost: the copy is dropped until a new image arrives; ask for one.
    Gap,
    /// The primary stepped down and the copy is complete: take over.
    SteppingDown,
}

/// A standby's end: a copy of the primary's core, kept current record by record.
#[derive(Debug, Default)]
pub struct Follower {
    core: Option<Broker>,
    seq: u64,
}

impl Follower {
    /// An empty follower, waiting for an image.
    pub fn new() -> Self {
        Follower::default()
    }

    /// The copy, if it is complete.
    pub fn core(&self) -> Option<&Broker> {
        self.core.as_ref()
    }

    /// The last op applied.
    pub fn seq(&self) -> u64 {
        self.seq
    }

    /// Whether the copy is complete (an image and every op since).
    pub fn synced(&self) -> bool {
        self.core.is_some()
    }

    /// Takes the copy out, to run it as the primary.
    pub fn into_core(self) -> Option<Broker> {
        self.core
    }

    /// Checks one archived record in place and applies it.
    pub fn apply(&mut self, bytes: &[u8]) -> Result<Step, ReplicaError> {
        let record = rkyv::access::<ArchivedRecord, rancor::Error>(bytes)
            .map_err(|e| ReplicaError::Malformed(e.to_string()))?;
        let de = |e: rancor::Error| ReplicaError::Malformed(e.to_string());
        Ok(match record {
            ArchivedRecord::Image(seq, core) => {
                let seq = seq.to_native();
                if self.core.is_some() && seq <= self.seq {
                    return Ok(Step::Ignored);
                }
                let mut core: Broker =
                    rkyv::deserialize::<Broker, rancor::Error>(core).map_err(de)?;
                // Outputs are the primary's to send; a copy only keeps state.
                core.discard_outputs();
                self.core = Some(core);
                self.seq = seq;
                Step::Applied
            }
            ArchivedRecord::Op(seq, now, op) => {
                let seq = seq.to_native();
                let Some(core) = self.core.as_mut() else {
                    return Ok(Step::Ignored);
                };
                if seq <= self.seq {
                    return Ok(Step::Ignored);
                }
                if seq != self.seq + 1 {
                    self.core = None;
                    return Ok(Step::Gap);
                }
                let now: Duration =
                    rkyv::deserialize::<Duration, rancor::Error>(now).map_err(de)?;
                let op: Op = rkyv::deserialize::<Op, rancor::Error>(op).map_err(de)?;
                core.apply(now, op);
                core.discard_outputs();
                self.seq = seq;
                Step::Applied
            }
            ArchivedRecord::Heartbeat(seq) => {
                if self.core.is_some() && seq.to_native() > self.seq {
                    self.core = None;
                    return Ok(Step::Gap);
                }
                Step::Ignored
            }
            ArchivedRecord::SteppingDown(seq) => {
                if self.core.is_some() && seq.to_native() == self.seq {
                    Step::SteppingDown
                } else {
                    if self.core.is_some() && seq.to_native() > self.seq {
                        self.core = None;
                    }
                    Step::Gap
                }
            }
        })
    }
}

// A borrowing twin of [`Record`], archived exactly like it: the primary archives its
// state without copying it first.
#[derive(rkyv::Archive, rkyv::Serialize)]
#[rkyv(as = ArchivedRecord)]
#[allow(dead_code)] // only ever archived
enum RecordRef<'a> {
    Image(u64, #[rkyv(with = rkyv::with::Inline)] &'a Broker),
    Op(u64, Duration, #[rkyv(with = rkyv::with::Inline)] &'a Op),
    Heartbeat(u64),
    SteppingDown(u64),
}

fn archive(r: &RecordRef<'_>) -> AlignedVec {
    rkyv::to_bytes::<rancor::Error>(r).expect("replication records always archive")
}

#[cfg(test)]
#[path = "replica_tests.rs"]
#[allow(clippy::unwrap_used)]
mod tests;
