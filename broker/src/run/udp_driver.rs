//! The UDP front's driver: its socket and access file around the sans-IO front.

#[allow(unused_imports)]
use super::*;

/// The UDP front's socket and access file around the sans-IO [`UdpFront`].
pub(super) struct UdpDriver {
    pub(super) sock: UdpSocket,
    pub(super) front: UdpFront,
    pub(super) access_path: Option<PathBuf>,
}

impl UdpDriver {
    pub(super) fn bind(cfg: UdpConfig, epoch: u64) -> Result<Self, UdpError> {
        let access = match &cfg.access_path {
            Some(p) => AccessFile::load(p).map_err(UdpError::Access)?,
            None => AccessFile::default(),
        };
        let sock = UdpSocket::bind(cfg.bind).map_err(|e| UdpError::Bind(cfg.bind, e))?;
        sock.set_nonblocking(true)
            .map_err(|e| UdpError::Bind(cfg.bind, e))?;
        match size_recv_buffer(&sock) {
            Ok(n) if n < muster_shared::udp::RECV_BUFFER => tracing::info!(
                "udp receive buffer {n} bytes (asked {}): raise net.core.rmem_max for bursts of handshakes",
                muster_shared::udp::RECV_BUFFER
            ),
            Ok(_) => {}
            Err(e) => tracing::warn!("cannot size the udp receive buffer: {e}"),
        }
        let local = sock.local_addr().map_err(|e| UdpError::Bind(cfg.bind, e))?;
        let seed: [u8; 32] = rand::rng().random();
        let front = UdpFront::new(
            cfg.key,
            access,
            cfg.limits,
            local,
            epoch,
            Instant::now(),
            seed,
        );
        Ok(UdpDriver {
            sock,
            front,
            access_path: cfg.access_path,
        })
    }

    /// Reads every waiting datagram (at most a few thousand a call, so one flood cannot
    /// starve the shared-memory side), handing the front's messages to the core.
    pub(super) fn on_readable(
        &mut self,
        handling: &mut Handling,
        core: &mut Broker,
        fed: Fed,
        now: Duration,
    ) {
        let mut buf = [0u8; MAX_DATAGRAM + 1];
        for _ in 0..RECV_BATCH {
            let Some((n, from)) = recv_one(&self.sock, &mut buf) else {
                break;
            };
            self.front.handle(Instant::now(), from, &buf[..n], core);
            self.events(handling, core, fed, now);
        }
        self.transmit();
    }

    /// Re-reads the access file (SIGHUP); a bad file keeps the old one.
    pub(super) fn reload(
        &mut self,
        handling: &mut Handling,
        core: &mut Broker,
        fed: Fed,
        now: Duration,
    ) {
        let Some(path) = &self.access_path else {
            return;
        };
        match AccessFile::load(path) {
            Ok(a) => self.front.reload(Instant::now(), a),
            Err(e) => tracing::error!("{e}; keeping the previous access file"),
        }
        self.events(handling, core, fed, now);
        self.transmit();
    }

    pub(super) fn housekeeping(
        &mut self,
        handling: &mut Handling,
        core: &mut Broker,
        fed: Fed,
        now: Duration,
    ) {
        self.front.handle_timeout(Instant::now());
        self.events(handling, core, fed, now);
        self.transmit();
    }

    /// The front's messages for the core; a federation takes requests for other
    /// hosts' services first, and hears of remote users gone.
    pub(super) fn events(
        &mut self,
        handling: &mut Handling,
        core: &mut Broker,
        fed: Fed,
        now: Duration,
    ) {
        while let Some(ev) = self.front.poll_event() {
            match ev {
                FrontEvent::ToCore(msg) => {
                    let front = &mut self.front;
                    let passed_on = fed.as_mut().is_some_and(|f| {
                        f.intercept(&msg, |user, req| front.remote_contact(user, req))
                    });
                    if !passed_on {
                        timed_handle(handling, core, now, msg)
                    }
                }
                FrontEvent::UserGone(u) => {
                    if let Some(f) = fed.as_mut() {
                        f.local_user_gone(&u);
                    }
                    core.user_died(now, &u)
                }
                FrontEvent::Revoked(u) => {
                    if let Some(f) = fed.as_mut() {
                        f.local_user_gone(&u);
                    }
                    core.revoke(now, &u)
                }
            }
        }
    }

    pub(super) fn transmit(&mut self) {
        while let Some(t) = self.front.poll_transmit() {
            send_transmit(&self.sock, &t, &mut self.front.stats_mut().drops);
        }
    }
}
