//! One MQTT connection (rumqttc's blocking client) on a thread of its own, handing
//! what arrives to the system's thread through a channel and a socket the system's
//! reactor sleeps on. It subscribes again after every reconnect.

use crate::VdaFail;
use rumqttc::{Client, Event, LastWill, MqttOptions, Packet, QoS};
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, RawFd};
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender};
use std::sync::Arc;
use std::time::Duration;

/// Largest message taken or sent, bytes (a state with a long order is tens of KiB).
pub const MAX_PACKET: usize = 1 << 20;
/// How long the thread waits between tries while the MQTT broker cannot be reached.
const RETRY: Duration = Duration::from_millis(500);

/// How to reach a broker that asks for more than a plain connection.
#[derive(Clone, Default)]
pub struct MqttSecurity {
    /// TLS, trusting the certificate authorities in this PEM file (the broker's
    /// certificate must name the host or IP address of `broker`).
    pub ca: Option<std::path::PathBuf>,
    /// With TLS: this client's certificate chain and key (PEM), for brokers that ask
    /// for one (`require_certificate true`).
    pub client_cert: Option<(std::path::PathBuf, std::path::PathBuf)>,
    /// User name and password (sent only over TLS unless the caller accepts a plain
    /// connection).
    pub credentials: Option<(String, String)>,
}

/// The password is never printed.
impl std::fmt::Debug for MqttSecurity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MqttSecurity")
            .field("ca", &self.ca)
            .field("client_cert", &self.client_cert)
            .field("user", &self.credentials.as_ref().map(|(u, _)| u))
            .finish()
    }
}

impl MqttSecurity {
    /// Reads the password of `user` from `file` (its first line): never on a command
    /// line, where other users of the host could read it.
    pub fn password_from(user: &str, file: &std::path::Path) -> Result<(String, String), VdaFail> {
        let text = std::fs::read_to_string(file)
            .map_err(|e| VdaFail::Config(format!("password file {}: {e}", file.display())))?;
        let pass = text
            .lines()
            .next()
            .unwrap_or_default()
            .trim_end()
            .to_string();
        if pass.is_empty() {
            return Err(VdaFail::Config(format!(
                "password file {} is empty",
                file.display()
            )));
        }
        Ok((user.to_string(), pass))
    }

    /// The rustls client configuration for [`MqttSecurity::ca`], if TLS is asked for.
    fn tls(&self) -> Result<Option<rustls::ClientConfig>, VdaFail> {
        let Some(ca) = &self.ca else {
            if self.client_cert.is_some() {
                return Err(VdaFail::Config(
                    "a client certificate needs TLS: give the CA too".into(),
                ));
            }
            return Ok(None);
        };
        let bad = |what: &str, e: &dyn std::fmt::Display| VdaFail::Config(format!("{what}: {e}"));
        let pem = |p: &std::path::Path| -> Result<Vec<u8>, VdaFail> {
            std::fs::read(p).map_err(|e| bad(&p.display().to_string(), &e))
        };
        let mut roots = rustls::RootCertStore::empty();
        let ca_pem = pem(ca)?;
        for cert in rustls_pemfile::certs(&mut ca_pem.as_slice()) {
            let cert = cert.map_err(|e| bad(&ca.display().to_string(), &e))?;
            roots
                .add(cert)
                .map_err(|e| bad(&ca.display().to_string(), &e))?;
        }
        if roots.is_empty() {
            return Err(VdaFail::Config(format!(
                "{}: no certificate in it",
                ca.display()
            )));
        }
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .map_err(|e| bad("TLS", &e))?
            .with_root_certificates(roots);
        let config = match &self.client_cert {
            None => builder.with_no_client_auth(),
            Some((cert, key)) => {
                let chain_pem = pem(cert)?;
                let chain = rustls_pemfile::certs(&mut chain_pem.as_slice())
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|e| bad(&cert.display().to_string(), &e))?;
                let key_pem = pem(key)?;
                let key = rustls_pemfile::private_key(&mut key_pem.as_slice())
                    .map_err(|e| bad(&key.display().to_string(), &e))?
                    .ok_or_else(|| {
                        VdaFail::Config(format!("{}: no private key in it", key.display()))
                    })?;
                builder
                    .with_client_auth_cert(chain, key)
                    .map_err(|e| bad("client certificate", &e))?
            }
        };
        Ok(Some(config))
    }
}

/// What to connect to and ask for.
#[derive(Clone, Debug)]
pub struct MqttConfig {
    /// `host:port` of the MQTT broker.
    pub broker: String,
    /// TLS and credentials, if the broker asks for them.
    pub security: MqttSecurity,
    /// This client's id (unique per broker).
    pub client_id: String,
    /// Keep-alive: the broker sends the last will after 1.5 times this of silence.
    pub keep_alive: Duration,
    /// Topic filters to subscribe to (QoS 1), again after each reconnect.
    pub subscriptions: Vec<String>,
    /// The last will: topic, payload, retained (QoS 1).
    pub will: Option<(String, Vec<u8>, bool)>,
}

/// What the connection heard.
#[derive(Clone, Debug, PartialEq)]
pub enum Incoming {
    /// Connected (again) and subscribed.
    Connected,
    /// A message.
    Publish {
        /// Its topic.
        topic: String,
        /// Its payload.
        payload: Vec<u8>,
        /// Whether the broker kept it (sent because we subscribed, not just now).
        retained: bool,
    },
    /// The connection broke; the thread retries.
    Down(String),
}

/// A connection to an MQTT broker.
pub struct MqttLink {
    client: Client,
    rx: Receiver<Incoming>,
    wake: UnixStream,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

fn split_addr(broker: &str) -> Result<(String, u16), VdaFail> {
    let (host, port) = broker
        .rsplit_once(':')
        .ok_or_else(|| VdaFail::Config(format!("--mqtt {broker:?}: give HOST:PORT")))?;
    let port: u16 = port
        .parse()
        .map_err(|_| VdaFail::Config(format!("--mqtt {broker:?}: bad port")))?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() {
        return Err(VdaFail::Config(format!("--mqtt {broker:?}: no host")));
    }
    Ok((host.to_string(), port))
}

impl MqttLink {
    /// Starts connecting to `cfg.broker` (the thread keeps trying while it is down).
    pub fn connect(cfg: &MqttConfig) -> Result<Self, VdaFail> {
        let (host, port) = split_addr(&cfg.broker)?;
        let mut opts = MqttOptions::new(cfg.client_id.clone(), host, port);
        opts.set_keep_alive(cfg.keep_alive)
            .set_clean_session(true)
            .set_max_packet_size(MAX_PACKET, MAX_PACKET);
        if let Some(tls) = cfg.security.tls()? {
            opts.set_transport(rumqttc::Transport::tls_with_config(
                rumqttc::TlsConfiguration::Rustls(Arc::new(tls)),
            ));
        }
        if let Some((user, pass)) = &cfg.security.credentials {
            opts.set_credentials(user.clone(), pass.clone());
        }
        if let Some((topic, payload, retain)) = &cfg.will {
            opts.set_last_will(LastWill::new(
                topic.clone(),
                payload.clone(),
                QoS::AtLeastOnce,
                *retain,
            ));
        }
        let (client, mut connection) = Client::new(opts, 1024);
        // Small messages both ways (an order, then the vehicle's acknowledgement): no
        // Nagle delay (measured: 40 ms tails on loopback with it, the delayed-ACK timer).
        let mut net = rumqttc::NetworkOptions::new();
        net.set_tcp_nodelay(true);
        connection.eventloop.set_network_options(net);
        let (wake, mut tx_wake) =
            UnixStream::pair().map_err(|e| VdaFail::Config(format!("socketpair: {e}")))?;
        wake.set_nonblocking(true)
            .map_err(|e| VdaFail::Config(format!("socketpair: {e}")))?;
        let _ = tx_wake.set_nonblocking(true);
        let (tx, rx) = std::sync::mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let subs = cfg.subscriptions.clone();
        let sub_client = client.clone();
        let stopping = stop.clone();
        let thread = std::thread::Builder::new()
            .name("mqtt".into())
            .spawn(move || {
                let send = |tx: &Sender<Incoming>, w: &mut UnixStream, m: Incoming| {
                    let ok = tx.send(m).is_ok();
                    // A full socket already wakes the reader.
                    let _ = w.write(b".");
                    ok
                };
                let mut down_said = false;
                // A blocking receive: a timeout around it would drop the event loop's
                // poll half way through a packet. `close` wakes it with a disconnect.
                while !stopping.load(Ordering::Relaxed) {
                    let event = match connection.recv() {
                        Err(_) => break, // every client handle is gone
                        Ok(e) => e,
                    };
                    let m = match event {
                        Ok(Event::Incoming(Packet::ConnAck(_))) => {
                            down_said = false;
                            for s in &subs {
                                if let Err(e) =
                                    sub_client.try_subscribe(s.clone(), QoS::AtLeastOnce)
                                {
                                    tracing::warn!("MQTT subscribe {s}: {e}");
                                }
                            }
                            Incoming::Connected
                        }
                        Ok(Event::Incoming(Packet::Publish(p))) => {
                            tracing::trace!(topic = %p.topic, bytes = p.payload.len(), "MQTT in");
                            Incoming::Publish {
                                topic: p.topic,
                                payload: p.payload.to_vec(),
                                retained: p.retain,
                            }
                        }
                        Ok(_) => continue,
                        Err(e) => {
                            if stopping.load(Ordering::Relaxed) {
                                break;
                            }
                            let said = std::mem::replace(&mut down_said, true);
                            std::thread::sleep(RETRY);
                            if said {
                                continue;
                            }
                            Incoming::Down(e.to_string())
                        }
                    };
                    if !send(&tx, &mut tx_wake, m) {
                        break;
                    }
                }
            })
            .map_err(|e| VdaFail::Config(format!("thread: {e}")))?;
        Ok(MqttLink {
            client,
            rx,
            wake,
            stop,
            thread: Some(thread),
        })
    }

    /// A descriptor readable when something arrived (edge-triggered: call
    /// [`MqttLink::drain`]).
    pub fn fd(&self) -> RawFd {
        self.wake.as_raw_fd()
    }

    /// Everything that arrived, oldest first.
    pub fn drain(&mut self) -> Vec<Incoming> {
        let mut buf = [0u8; 256];
        while (&self.wake).read(&mut buf).is_ok_and(|n| n > 0) {}
        self.rx.try_iter().collect()
    }

    /// Waits up to `timeout` for something to arrive (for use before a reactor runs).
    pub fn wait(&mut self, timeout: Duration) -> Option<Incoming> {
        self.rx.recv_timeout(timeout).ok()
    }

    /// Sends `payload` on `topic` at QoS 1, without waiting for the broker: an error
    /// means the outgoing queue is full or the connection is gone for good.
    pub fn publish(&self, topic: &str, payload: Vec<u8>, retain: bool) -> Result<(), String> {
        self.client
            .try_publish(topic, QoS::AtLeastOnce, retain, payload)
            .map_err(|e| e.to_string())
    }

    /// Disconnects in order (no last will) and stops the thread.
    pub fn close(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // The disconnect goes out through the thread's event loop, which wakes for it
        // and sees the stop; while the broker is unreachable it is between tries.
        let _ = self.client.try_disconnect();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for MqttLink {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.close();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broker_addresses() {
        assert_eq!(
            split_addr("127.0.0.1:1883").unwrap(),
            ("127.0.0.1".into(), 1883)
        );
        assert_eq!(split_addr("[::1]:1884").unwrap(), ("::1".into(), 1884));
        for bad in ["localhost", ":1883", "h:port", "h:70000"] {
            assert!(split_addr(bad).is_err(), "{bad}");
        }
    }
}
