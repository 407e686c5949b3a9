//! The primary's replication stream to its standbys.

#[allow(unused_imports)]
use super::*;

/// The primary's replication stream to its standbys.
pub(super) struct Replication {
    pub(super) writer: ReplicaWriter,
    pub(super) leader: Leader,
    /// A standby asked for the whole state.
    pub(super) image_owed: bool,
    /// When the last image went: images go at most every [`IMAGE_EVERY`], however
    /// often the standby bell rings (any process of the account can ring it).
    pub(super) last_image: Option<Instant>,
    pub(super) last_sent: Instant,
}

/// No progress of the loop for this long, outside its wait for work, is a stall the
/// watchdog logs.
pub(super) const STALL: Duration = Duration::from_secs(1);

/// How long a primary stepping down waits for a standby to take over or to leave.
pub(super) const HANDOVER_WAIT: Duration = Duration::from_secs(2);

/// Least time between two state images to the standbys.
const IMAGE_EVERY: Duration = Duration::from_millis(100);

impl Replication {
    /// Publishes the core's journal, then the image if one is owed; rings if anything went.
    pub(super) fn publish(&mut self, core: &mut Broker) {
        let mut sent = false;
        for record in self.leader.ops(core) {
            if let Err(e) = self.writer.publish(&record) {
                tracing::warn!("replication: {e}");
            }
            sent = true;
        }
        if self.image_due() == Some(Duration::ZERO) {
            self.image_owed = false;
            self.last_image = Some(Instant::now());
            let image = self.leader.image(core);
            match self.writer.publish(&image) {
                Ok(()) => tracing::info!(
                    bytes = image.len(),
                    seq = self.leader.seq(),
                    standbys = self.writer.standbys(),
                    "state image sent to standbys"
                ),
                Err(e) => tracing::warn!("replication image: {e}"),
            }
            sent = true;
        }
        if sent {
            self.writer.ring();
            self.last_sent = Instant::now();
        }
    }

    /// When the owed image may go, if one is owed.
    pub(super) fn image_due(&self) -> Option<Duration> {
        self.image_owed.then(|| {
            self.last_image
                .map_or(Duration::ZERO, |t| IMAGE_EVERY.saturating_sub(t.elapsed()))
        })
    }

    /// When a heartbeat is due, if standbys follow.
    pub(super) fn heartbeat_due(&self) -> Option<Duration> {
        (self.writer.standbys() > 0).then(|| HEARTBEAT.saturating_sub(self.last_sent.elapsed()))
    }

    pub(super) fn heartbeat(&mut self) {
        if self.heartbeat_due() == Some(Duration::ZERO) {
            let _ = self.writer.publish(&self.leader.heartbeat());
            self.writer.ring();
            self.last_sent = Instant::now();
        }
    }
}
