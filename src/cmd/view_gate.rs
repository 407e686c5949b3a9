//! The door of `muster view`: one TCP port in front of its Foxglove WebSocket server
//! (which listens on a loopback port of its own and never serves the broker's event
//! feed). The gate counts connections (one past the limit gets `503` and is closed),
//! reads each WebSocket upgrade request (at most 8 KiB, within 5 s) and sends it to the
//! Foxglove server, copying bytes both ways; a request for `/events` with the
//! operators' token (`?token=...`; without it, or a wrong one: `403`) is answered here,
//! with the event feed: one JSON record per text message, as `muster events` prints.
//! A viewer that reads nothing for 5 s while the gate has bytes for it (its socket full)
//! is let go; until then the Foxglove server keeps at most `message_backlog_size`
//! messages for it (dropping the oldest). An operator is let go likewise, or when 256
//! records wait for it. Memory goes back with the connection.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Longest upgrade request read.
const MAX_HEAD: usize = 8 * 1024;
/// How long a client has to send its upgrade request.
const HEAD_TIMEOUT: Duration = Duration::from_secs(5);

/// Records waiting for one operator; beyond, it is dropped.
const OPERATOR_BACKLOG: usize = 256;
/// How long a write to a viewer or an operator may block: one that reads nothing for
/// this long (its socket full) is let go.
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);

/// Where the gate sends a client.
#[derive(Clone, Debug)]
pub struct Backends {
    /// The Foxglove server.
    pub foxglove: SocketAddr,
    /// The operators' token for `/events`.
    pub token: String,
}

/// The event feed's operators: each record goes to each, or the slow one is dropped.
#[derive(Clone, Default)]
pub struct Feed {
    operators: Arc<Mutex<Vec<SyncSender<Arc<str>>>>>,
}

impl Feed {
    /// Sends `record` (JSON) to every operator connected; one whose backlog is full is
    /// let go.
    pub fn send(&self, record: &str) {
        let Ok(mut ops) = self.operators.lock() else {
            return;
        };
        if ops.is_empty() {
            return;
        }
        let r: Arc<str> = Arc::from(record);
        ops.retain(|tx| match tx.try_send(r.clone()) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) => {
                tracing::info!("view: an operator too slow for the event feed: dropped");
                false
            }
            Err(TrySendError::Disconnected(_)) => false,
        });
    }

    fn join(&self) -> Receiver<Arc<str>> {
        let (tx, rx) = sync_channel(OPERATOR_BACKLOG);
        if let Ok(mut ops) = self.operators.lock() {
            ops.push(tx);
        }
        rx
    }
}

/// A running gate; dropping it stops taking connections.
pub struct Gate {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    accept: Option<std::thread::JoinHandle<()>>,
}

impl Gate {
    /// Listens on `listen` and serves up to `max_clients` connections at once.
    pub fn start(
        listen: SocketAddr,
        to: Backends,
        feed: Feed,
        max_clients: usize,
    ) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(listen)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let active = Arc::new(AtomicUsize::new(0));
        let to = Arc::new(to);
        let s = stop.clone();
        let accept = std::thread::Builder::new()
            .name("view-gate".into())
            .spawn(move || {
                for conn in listener.incoming() {
                    if s.load(Ordering::Acquire) {
                        break;
                    }
                    let Ok(conn) = conn else { continue };
                    if active.load(Ordering::Acquire) >= max_clients {
                        refuse(conn, "503 Service Unavailable", "too many viewers");
                        continue;
                    }
                    active.fetch_add(1, Ordering::AcqRel);
                    let (to, active, feed) = (to.clone(), active.clone(), feed.clone());
                    let spawned = std::thread::Builder::new()
                        .name("view-client".into())
                        .spawn(move || {
                            let _left = Leaves(&active);
                            if let Err(e) = serve(conn, &to, &feed) {
                                tracing::debug!("view client: {e}");
                            }
                        });
                    if let Err(e) = spawned {
                        tracing::warn!("view: cannot serve a client: {e}");
                    }
                }
            })?;
        Ok(Gate {
            addr,
            stop,
            accept: Some(accept),
        })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for Gate {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        // Wake the accept loop with a connection of our own.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(200));
        if let Some(t) = self.accept.take() {
            let _ = t.join();
        }
    }
}

/// Counts a client out when its thread ends.
struct Leaves<'a>(&'a AtomicUsize);

impl Drop for Leaves<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

fn refuse(mut conn: TcpStream, status: &str, why: &str) {
    let _ = conn.set_write_timeout(Some(Duration::from_millis(200)));
    let _ = write!(
        conn,
        "HTTP/1.1 {status}\r\nContent-Type: text/plain\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{why}\n",
        why.len() + 1
    );
    let _ = conn.shutdown(Shutdown::Both);
}

/// The path and the token in a request line (`GET /events?token=T HTTP/1.1`).
fn target_of(head: &[u8]) -> (String, Option<String>) {
    let line = head
        .split(|&b| b == b'\r' || b == b'\n')
        .next()
        .unwrap_or_default();
    let target = std::str::from_utf8(line)
        .ok()
        .and_then(|l| l.split(' ').nth(1))
        .unwrap_or("/");
    let (path, query) = target.split_once('?').unwrap_or((target, ""));
    let token = query
        .split('&')
        .find_map(|kv| kv.strip_prefix("token="))
        .map(str::to_string);
    (path.to_string(), token)
}

/// Whether `a` and `b` are equal, in time that does not depend on where they differ.
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

fn serve(mut conn: TcpStream, to: &Backends, feed: &Feed) -> std::io::Result<()> {
    conn.set_read_timeout(Some(HEAD_TIMEOUT))?;
    let mut head = Vec::with_capacity(1024);
    let mut buf = [0u8; 1024];
    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
        if head.len() >= MAX_HEAD {
            refuse(
                conn,
                "431 Request Header Fields Too Large",
                "request too large",
            );
            return Ok(());
        }
        let n = conn.read(&mut buf)?;
        if n == 0 {
            return Ok(());
        }
        head.extend_from_slice(&buf[..n]);
    }
    let (path, token) = target_of(&head);
    if path.trim_end_matches('/') == "/events" {
        if !token.is_some_and(|t| same(&t, &to.token)) {
            refuse(
                conn,
                "403 Forbidden",
                "the event feed is for operators: give ?token=",
            );
            return Ok(());
        }
        return operator(conn, head, feed);
    }
    conn.set_read_timeout(None)?;
    conn.set_write_timeout(Some(WRITE_TIMEOUT))?;
    limit_send_buffer(&conn);
    let mut server = TcpStream::connect(to.foxglove)?;
    server.write_all(&head)?;
    let (mut c2, mut s2) = (conn.try_clone()?, server.try_clone()?);
    let up = std::thread::Builder::new()
        .name("view-client-up".into())
        .spawn(move || {
            let _ = std::io::copy(&mut c2, &mut s2);
            let _ = s2.shutdown(Shutdown::Write);
        })?;
    let _ = std::io::copy(&mut server, &mut conn);
    let _ = conn.shutdown(Shutdown::Both);
    let _ = server.shutdown(Shutdown::Both);
    let _ = up.join();
    Ok(())
}

/// Most bytes the kernel holds unsent for one viewer.
const SEND_BUFFER: libc::c_int = 256 * 1024;

/// Caps `conn`'s kernel send buffer at [`SEND_BUFFER`] (a slow viewer's unsent bytes).
fn limit_send_buffer(conn: &TcpStream) {
    use std::os::fd::AsRawFd;
    // SAFETY: setsockopt on a socket we own, with a pointer to a live c_int and its size.
    let r = unsafe {
        libc::setsockopt(
            conn.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_SNDBUF,
            std::ptr::from_ref(&SEND_BUFFER).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if r != 0 {
        tracing::debug!("view: SO_SNDBUF: {}", std::io::Error::last_os_error());
    }
}

/// A connection whose first bytes (the request already read) are read again.
struct Replayed {
    head: std::io::Cursor<Vec<u8>>,
    conn: TcpStream,
}

impl Read for Replayed {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self.head.read(buf)? {
            0 => self.conn.read(buf),
            n => Ok(n),
        }
    }
}

impl Write for Replayed {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.conn.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.conn.flush()
    }
}

/// An operator's WebSocket: the event feed, one record per text message.
fn operator(conn: TcpStream, head: Vec<u8>, feed: &Feed) -> std::io::Result<()> {
    use tungstenite::{Error, Message};
    conn.set_write_timeout(Some(WRITE_TIMEOUT))?;
    limit_send_buffer(&conn);
    let stream = Replayed {
        head: std::io::Cursor::new(head),
        conn,
    };
    let mut ws = tungstenite::accept(stream).map_err(std::io::Error::other)?;
    // Reads (pongs, a close) must not block the writes.
    ws.get_mut()
        .conn
        .set_read_timeout(Some(Duration::from_millis(1)))?;
    let records = feed.join();
    loop {
        match records.recv_timeout(Duration::from_secs(1)) {
            Ok(r) => ws.send(Message::text(r.to_string())),
            Err(RecvTimeoutError::Timeout) => ws.send(Message::Ping(Vec::new().into())),
            // Let go: too slow.
            Err(RecvTimeoutError::Disconnected) => {
                let _ = ws.close(None);
                let _ = ws.flush();
                return Ok(());
            }
        }
        .map_err(std::io::Error::other)?;
        match ws.read() {
            Ok(Message::Close(_)) | Err(Error::ConnectionClosed | Error::AlreadyClosed) => {
                return Ok(())
            }
            Ok(_) => {}
            Err(Error::Io(e))
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => return Err(std::io::Error::other(e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_path_and_token_are_read_from_the_request_line_only() {
        let t = |s: &str| target_of(s.as_bytes());
        assert_eq!(
            t("GET /events?token=abc HTTP/1.1\r\nHost: x\r\n\r\n"),
            ("/events".into(), Some("abc".into()))
        );
        assert_eq!(
            t("GET /x?a=1&token=z9 HTTP/1.1\r\n\r\n").1,
            Some("z9".into())
        );
        assert_eq!(
            t("GET / HTTP/1.1\r\nX: ?token=abc\r\n\r\n"),
            ("/".into(), None)
        );
        assert_eq!(t("GET /?tok=abc HTTP/1.1\r\n\r\n").1, None);
        assert_eq!(t("garbage").0, "/");
        assert!(same("abc", "abc") && !same("abc", "abd") && !same("abc", "ab"));
    }
}
