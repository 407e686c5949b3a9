//! `muster web`, over its HTTP and WebSocket protocol: sign-in, what a browser must not
//! be able to do (cross-origin requests, sockets without a session, sign-out without its
//! CSRF token, guessing tokens), and what each user may see and do (its access-file
//! patterns), with an operator acting on another user's session. The browser itself
//! drives the app in `web/tests/test_browser.py`.

#![allow(clippy::unwrap_used)]

mod common;

use common::{free_tcp_port, Fed};
use serde_json::{json, Value};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tungstenite::client::IntoClientRequest;
use tungstenite::{Message, WebSocket};

/// An HTTP answer: status, headers (names lower-case), body.
struct Answer {
    status: u16,
    headers: Vec<(String, String)>,
    body: String,
}

impl Answer {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    fn json(&self) -> Value {
        serde_json::from_str(&self.body).unwrap_or(Value::Null)
    }
}

/// One HTTP/1.1 request on a fresh connection, parsed.
fn http(port: u16, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> Answer {
    let text = common::http(
        &format!("127.0.0.1:{port}"),
        &format!("{method} {path} HTTP/1.1"),
        headers,
        body,
    );
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let mut lines = head.lines();
    let status = lines
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let headers = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    Answer {
        status,
        headers,
        body: body.to_string(),
    }
}

struct Web {
    /// `muster web`'s pid.
    pid: i32,
    /// The broker's index in `fed`.
    broker: usize,
    fed: Fed,
    port: u16,
    origin: String,
    dir: PathBuf,
    log: PathBuf,
}

impl Drop for Web {
    fn drop(&mut self) {
        self.fed.shutdown();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A broker, a data system `t1` (two `pose2d` services), a command system `d1` (one
/// `goal2d` service with a queue) and `muster web` with an access file: alice may use
/// `t1/*`, bob is an operator of everything, carol has a key but no web line.
fn setup(name: &str) -> Web {
    let users = [
        ("alice".to_string(), vec!["--web", "--allow", "t1/*"]),
        (
            "bob".to_string(),
            vec!["--web", "--operator", "--allow", "*"],
        ),
        ("carol".to_string(), vec!["--allow", "*"]),
    ];
    setup_with(name, &users, &[], 3)
}

/// A broker (`broker_args`), systems t1 (two data services, `quota` sessions each) and
/// d1 (a queued command service), the access file's `users` made by `muster keygen`
/// (name, its flags), and `muster web` on a free port.
fn setup_with(
    name: &str,
    users: &[(String, Vec<&str>)],
    broker_args: &[&str],
    quota: usize,
) -> Web {
    let mut fed = Fed::new(name);
    let dir = std::env::temp_dir().join(format!("muster-web-test-{}", fed.inst));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let d = dir.to_str().unwrap();
    let mut access = String::new();
    for (user, extra) in users {
        let mut args = vec!["keygen", "--user", user.as_str(), "--out", d];
        args.extend(extra);
        let (code, out) = fed.run(&args, Duration::from_secs(10));
        assert_eq!(code, 0, "keygen {user}");
        access.push_str(&out);
    }
    std::fs::write(dir.join("access"), &access).unwrap();
    let broker = fed.broker(broker_args);
    let quota = quota.to_string();
    fed.system("t1", &["--services", "2", "--quota", &quota]);
    fed.system(
        "d1",
        &[
            "--services",
            "1",
            "--kind",
            "command",
            "--queue",
            "--quota",
            "1",
        ],
    );
    fed.wait_list(Duration::from_secs(10), |l| l.len() == 3);
    let port = free_tcp_port();
    let log = dir.join("web.log");
    let listen = format!("127.0.0.1:{port}");
    let access_path = dir.join("access");
    // Its log in a file, to show no token is ever written there (debug level).
    let c = fed.command(&[
        "web",
        "--listen",
        &listen,
        "--access",
        access_path.to_str().unwrap(),
        "--wait",
        "2s",
    ]);
    let sh = format!("exec \"$0\" \"$@\" 2>{}", log.display());
    let program = c.get_program().to_owned();
    let args: Vec<_> = c.get_args().map(|a| a.to_owned()).collect();
    let mut wrapped = std::process::Command::new("sh");
    wrapped
        .arg("-c")
        .arg(sh)
        .arg(program)
        .args(args)
        .env("RUST_LOG", "debug");
    let web = fed.spawn_command(wrapped);
    let first = fed.proc(web).json(Duration::from_secs(20)).unwrap();
    assert_eq!(first["listen"], json!(listen));
    let pid = fed.proc(web).pid();
    Web {
        pid,
        broker,
        fed,
        port,
        origin: format!("http://127.0.0.1:{port}"),
        dir,
        log,
    }
}

impl Web {
    fn token(&self, user: &str) -> String {
        std::fs::read_to_string(self.dir.join(format!("{user}.web")))
            .unwrap()
            .trim()
            .to_string()
    }

    fn login(&self, user: &str, token: &str) -> Answer {
        let body = json!({"user": user, "token": token}).to_string();
        http(
            self.port,
            "POST",
            "/api/login",
            &[
                ("Origin", &self.origin),
                ("Content-Type", "application/json"),
            ],
            &body,
        )
    }

    /// Signs in; returns the cookie (`muster_session=...`) and the CSRF token.
    fn sign_in(&self, user: &str) -> (String, String) {
        let a = self.login(user, &self.token(user));
        assert_eq!(a.status, 200, "{user} signs in: {}", a.body);
        let cookie = a.header("set-cookie").unwrap();
        (
            cookie.split(';').next().unwrap().to_string(),
            a.json()["csrf"].as_str().unwrap().to_string(),
        )
    }

    fn socket(&self, cookie: Option<&str>, origin: Option<&str>) -> Result<Tab, u16> {
        let mut req = format!("ws://127.0.0.1:{}/ws", self.port)
            .into_client_request()
            .unwrap();
        if let Some(c) = cookie {
            req.headers_mut().insert("Cookie", c.parse().unwrap());
        }
        if let Some(o) = origin {
            req.headers_mut().insert("Origin", o.parse().unwrap());
        }
        let stream = TcpStream::connect(("127.0.0.1", self.port)).unwrap();
        // The upgrade waits for the user's broker connection (up to `--wait`); reads
        // after it are short, so a tab's frames can be waited for in a loop.
        stream
            .set_read_timeout(Some(Duration::from_secs(15)))
            .unwrap();
        match tungstenite::client(req, stream) {
            Ok((ws, _)) => {
                ws.get_ref()
                    .set_read_timeout(Some(Duration::from_millis(200)))
                    .unwrap();
                Ok(Tab { ws })
            }
            Err(tungstenite::HandshakeError::Failure(tungstenite::Error::Http(r))) => {
                Err(r.status().as_u16())
            }
            Err(e) => panic!("websocket: {e}"),
        }
    }
}

/// A signed-in tab's socket.
struct Tab {
    ws: WebSocket<TcpStream>,
}

impl Tab {
    fn send(&mut self, v: Value) {
        self.ws.send(Message::text(v.to_string())).unwrap();
    }

    /// The next frame, waiting up to `wait`.
    fn next(&mut self, wait: Duration) -> Option<Value> {
        let deadline = Instant::now() + wait;
        while Instant::now() < deadline {
            match self.ws.read() {
                Ok(Message::Text(t)) => return serde_json::from_str(t.as_str()).ok(),
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(_) => return None,
            }
        }
        None
    }

    /// Frames until one for which `want` holds (bounded by `wait`).
    fn until(&mut self, wait: Duration, want: impl Fn(&Value) -> bool) -> Option<Value> {
        let deadline = Instant::now() + wait;
        while Instant::now() < deadline {
            if let Some(f) = self.next(deadline - Instant::now()) {
                if want(&f) {
                    return Some(f);
                }
            }
        }
        None
    }
}

fn ids(state: &Value) -> Vec<String> {
    let mut v: Vec<String> = state["list"]["services"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["id"].as_str().unwrap().to_string())
        .collect();
    v.sort();
    v
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

#[test]
fn sign_in_takes_a_web_token_and_the_server_refuses_what_a_browser_must_not_do() {
    let w = setup("web-signin");
    let page = http(w.port, "GET", "/", &[], "");
    assert_eq!(page.status, 200);
    let csp = page.header("content-security-policy").unwrap();
    assert!(
        csp.contains("script-src 'self'") && !csp.contains("unsafe-inline"),
        "{csp}"
    );
    assert!(csp.contains("frame-ancestors 'none'"), "{csp}");
    assert_eq!(page.header("x-content-type-options"), Some("nosniff"));
    assert!(
        page.body.contains("<script src=\"/app.js\""),
        "the app is served"
    );
    assert!(!page.body.contains("<script>"), "no inline script");
    let js = http(w.port, "GET", "/app.js", &[], "");
    assert_eq!(js.status, 200);
    assert!(js
        .header("content-type")
        .unwrap()
        .starts_with("text/javascript"));

    // Wrong token, and a user with no web line: refused alike (failures 1 and 2).
    assert_eq!(w.login("alice", "0123").status, 401);
    let carol = w.login("carol", &w.token("alice"));
    assert_eq!(carol.status, 401);
    assert_eq!(carol.json()["error"], json!("wrong user name or token"));
    // Cross-origin, origin-less and non-JSON sign-ins are refused before any check.
    let body = json!({"user": "alice", "token": w.token("alice")}).to_string();
    let no_origin = http(
        w.port,
        "POST",
        "/api/login",
        &[("Content-Type", "application/json")],
        &body,
    );
    assert_eq!(no_origin.status, 403);
    let evil = http(
        w.port,
        "POST",
        "/api/login",
        &[
            ("Origin", "http://evil.example"),
            ("Content-Type", "application/json"),
        ],
        &body,
    );
    assert_eq!(evil.status, 403);
    let form = http(
        w.port,
        "POST",
        "/api/login",
        &[
            ("Origin", &w.origin),
            ("Content-Type", "application/x-www-form-urlencoded"),
        ],
        "user=alice",
    );
    assert_eq!(form.status, 400);

    // The right token: an HttpOnly, SameSite=Strict cookie and a CSRF token.
    let ok = w.login("alice", &w.token("alice"));
    assert_eq!(ok.status, 200, "{}", ok.body);
    let set = ok.header("set-cookie").unwrap();
    assert!(
        set.contains("HttpOnly") && set.contains("SameSite=Strict"),
        "{set}"
    );
    assert_eq!(ok.json()["user"], json!("alice"));
    assert_eq!(ok.json()["operator"], json!(false));
    let cookie = set.split(';').next().unwrap().to_string();
    let csrf = ok.json()["csrf"].as_str().unwrap().to_string();
    let me = http(w.port, "GET", "/api/me", &[("Cookie", &cookie)], "");
    assert_eq!(me.json()["user"], json!("alice"));
    assert_eq!(http(w.port, "GET", "/api/me", &[], "").status, 401);

    // Sockets: a session and this server's origin, or nothing.
    assert_eq!(w.socket(None, Some(&w.origin)).err(), Some(401));
    assert_eq!(
        w.socket(Some(&cookie), Some("http://evil.example")).err(),
        Some(403)
    );
    assert_eq!(w.socket(Some(&cookie), None).err(), Some(403));
    let mut tab = w.socket(Some(&cookie), Some(&w.origin)).ok().unwrap();
    assert_eq!(
        tab.next(Duration::from_secs(5)).unwrap()["t"],
        json!("state")
    );

    // Sign-out needs the CSRF token; after it the cookie is worth nothing and the open
    // socket is closed.
    let no_csrf = http(
        w.port,
        "POST",
        "/api/logout",
        &[("Cookie", &cookie), ("Origin", &w.origin)],
        "",
    );
    assert_eq!(no_csrf.status, 403);
    let out = http(
        w.port,
        "POST",
        "/api/logout",
        &[
            ("Cookie", &cookie),
            ("Origin", &w.origin),
            ("X-CSRF-Token", &csrf),
        ],
        "",
    );
    assert_eq!(out.status, 200);
    assert_eq!(
        http(w.port, "GET", "/api/me", &[("Cookie", &cookie)], "").status,
        401
    );
    let closed = tab.until(Duration::from_secs(5), |f| f["t"] == json!("closed"));
    assert_eq!(closed.unwrap()["reason"], json!("signed out"));

    // Guessing: failures 3 to 5 are answered, then this address waits (even with the
    // right token), with Retry-After.
    for _ in 0..3 {
        assert_eq!(w.login("alice", "guess").status, 401);
    }
    let blocked = w.login("alice", &w.token("alice"));
    assert_eq!(blocked.status, 429, "{}", blocked.body);
    let retry: u64 = blocked.header("retry-after").unwrap().parse().unwrap();
    assert!((1..=60).contains(&retry), "{retry}");

    // No token, cookie or CSRF token ever reaches the log (debug level).
    let log = read(&w.log);
    assert!(
        log.contains("signed in on the web"),
        "the log is read: {log}"
    );
    for secret in [
        w.token("alice"),
        w.token("bob"),
        cookie.replace("muster_session=", ""),
        csrf,
    ] {
        assert!(!log.contains(&secret), "a secret in the log");
    }
}

#[test]
fn a_web_user_sees_and_gets_only_what_its_patterns_allow_and_operators_act_on_any_session() {
    let w = setup("web-access");
    let (alice_cookie, _) = w.sign_in("alice");
    let (bob_cookie, _) = w.sign_in("bob");
    let mut alice = w.socket(Some(&alice_cookie), Some(&w.origin)).ok().unwrap();
    let mut bob = w.socket(Some(&bob_cookie), Some(&w.origin)).ok().unwrap();
    let a0 = alice.next(Duration::from_secs(10)).unwrap();
    let b0 = bob.next(Duration::from_secs(10)).unwrap();
    assert_eq!(
        ids(&a0),
        ["t1/s0", "t1/s1"],
        "alice lists t1's services only"
    );
    assert_eq!(ids(&b0), ["d1/s0", "t1/s0", "t1/s1"]);
    assert_eq!(
        (a0["operator"].clone(), b0["operator"].clone()),
        (json!(false), json!(true))
    );

    // What alice may not use is refused as an unknown service would be, asked for
    // directly or through a link; operators' actions are not hers.
    alice.send(json!({"op": "request", "service": "d1/s0"}));
    let r = alice
        .until(Duration::from_secs(5), |f| f["t"] == json!("refused"))
        .unwrap();
    assert_eq!(
        (r["service"].clone(), r["code"].clone()),
        (json!("d1/s0"), json!("unknown"))
    );
    alice.send(json!({"op": "link", "data": "t1/s0", "command": "d1/s0"}));
    let l = alice
        .until(Duration::from_secs(5), |f| f["t"] == json!("link_refused"))
        .unwrap();
    assert!(l["error"].as_str().unwrap().contains("d1/s0"), "{l}");
    alice.send(json!({"op": "withdraw", "service": "t1/s0"}));
    let e = alice
        .until(Duration::from_secs(5), |f| f["t"] == json!("error"))
        .unwrap();
    assert_eq!(e["error"], json!("operators only"));
    alice.send(json!({"op": "nonsense"}));
    let e = alice
        .until(Duration::from_secs(5), |f| f["t"] == json!("error"))
        .unwrap();
    assert!(
        e["error"].as_str().unwrap().starts_with("bad message"),
        "{e}"
    );

    // What she may use streams: a session and updates in order.
    alice.send(json!({"op": "request", "service": "t1/s0"}));
    let g = alice
        .until(Duration::from_secs(10), |f| f["t"] == json!("granted"))
        .unwrap();
    let session = g["session"].as_str().unwrap().to_string();
    let mut seqs = Vec::new();
    while seqs.len() < 3 {
        let u = alice
            .until(Duration::from_secs(5), |f| f["t"] == json!("update"))
            .expect("updates stream");
        assert_eq!(u["session"], json!(session));
        assert_eq!(u["value"]["type"], json!("pose2d"));
        seqs.push(u["seq"].as_u64().unwrap());
    }
    assert!(seqs.windows(2).all(|p| p[1] > p[0]), "{seqs:?}");
    // Bob's list shows it in use: only what changed comes (the list changes for every
    // watcher).
    let in_use = bob
        .until(Duration::from_secs(5), |f| {
            f["t"] == json!("list_delta")
                && f["set"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|s| s["id"] == json!("t1/s0") && s["in_use"] == json!(1))
        })
        .expect("bob sees t1/s0 in use");
    assert_eq!(
        in_use["set"].as_array().unwrap().len(),
        1,
        "only t1/s0 changed: {in_use}"
    );
    assert_eq!(in_use["removed"], json!([]));

    // Bob drives d1 to a goal: its status comes as it goes.
    bob.send(json!({"op": "request", "service": "d1/s0"}));
    let g = bob
        .until(Duration::from_secs(10), |f| f["t"] == json!("granted"))
        .unwrap();
    assert_eq!(g["kind"], json!("command"));
    let d1 = g["session"].as_str().unwrap().to_string();
    bob.send(json!({"op": "goal", "session": d1, "x": 2.0, "y": 1.0}));
    let working = bob.until(Duration::from_secs(10), |f| {
        f["t"] == json!("status") && f["session"] == json!(d1) && f["state"] == json!("working")
    });
    assert!(working.is_some(), "d1 works on the goal");
    bob.send(json!({"op": "goal", "session": d1, "x": "far", "y": 1.0}));
    let e = bob
        .until(Duration::from_secs(5), |f| f["t"] == json!("error"))
        .unwrap();
    assert!(
        e["error"].as_str().unwrap().starts_with("bad message"),
        "{e}"
    );

    // As an operator, bob sees alice's session under her web user and ends it.
    bob.send(json!({"op": "status"}));
    let st = bob
        .until(Duration::from_secs(5), |f| {
            f["t"] == json!("operated") && f["status"].is_object()
        })
        .unwrap();
    let row = st["status"]["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["session"] == json!(session))
        .cloned()
        .unwrap_or_else(|| panic!("alice's session {session} in the status: {st}"));
    assert!(
        row["user"].as_str().unwrap().starts_with("web-alice-"),
        "{row}"
    );
    // Withdrawn by bob, t1/s1 shows withdrawn on alice's list; restored, it is back.
    for (op, withdrawn) in [("withdraw", true), ("restore", false)] {
        bob.send(json!({"op": op, "service": "t1/s1"}));
        let d = alice.until(Duration::from_secs(10), |f| {
            f["t"] == json!("list_delta")
                && f["set"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|s| s["id"] == json!("t1/s1"))
        });
        let row = d.unwrap()["set"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["id"] == json!("t1/s1"))
            .cloned();
        assert_eq!(row.unwrap()["withdrawn"], json!(withdrawn), "after {op}");
    }
    bob.send(json!({"op": "end_session", "session": session}));
    let ended = alice
        .until(Duration::from_secs(10), |f| f["t"] == json!("ended"))
        .unwrap();
    assert_eq!(ended["session"], json!(session));

    // Alice's web line goes from the access file: her socket is closed, bob's is not.
    let access = read(&w.dir.join("access"));
    let without: String = access
        .lines()
        .filter(|l| !l.starts_with("web alice"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::thread::sleep(Duration::from_millis(1100)); // a new mtime, even on coarse clocks
    std::fs::write(w.dir.join("access"), without).unwrap();
    let closed = alice.until(Duration::from_secs(10), |f| f["t"] == json!("closed"));
    assert_eq!(closed.unwrap()["reason"], json!("signed out"));
    assert_eq!(
        http(w.port, "GET", "/api/me", &[("Cookie", &alice_cookie)], "").status,
        401
    );
    assert_eq!(
        http(w.port, "GET", "/api/me", &[("Cookie", &bob_cookie)], "").status,
        200
    );
    bob.send(json!({"op": "status"}));
    assert!(bob
        .until(Duration::from_secs(5), |f| f["t"] == json!("operated"))
        .is_some());
}

#[test]
fn the_web_benchmark_runs_its_clients_and_counts_every_update() {
    let Some(python) = common::python_with("websockets", "websockets") else {
        return;
    };
    let f = Fed::new("web-bench");
    let (code, out) = f.run(
        &[
            "bench",
            "web",
            "--clients",
            "6",
            "--procs",
            "2",
            "--duration",
            "3s",
            "--probes",
            "20",
            "--python",
            &python,
            "--json",
        ],
        Duration::from_secs(120),
    );
    assert_eq!(code, 0, "{out}");
    let r: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    assert_eq!(r["clients"], json!(6));
    assert_eq!(r["gaps"], json!(0), "{r}");
    assert_eq!(r["errors"], json!([]), "{r}");
    // Six sessions at 10 Hz for 3 s: about 180 updates, each timed.
    let updates = r["updates"].as_u64().unwrap();
    assert!((150..=200).contains(&updates), "{r}");
    assert_eq!(r["web_update"]["count"].as_u64().unwrap(), updates);
    assert_eq!(r["broker_request_before"]["count"], json!(20));
    assert_eq!(r["broker_request_during"]["count"], json!(20));
    assert!(r["web_rss_kib"].as_u64().unwrap() > 0);
}

/// Descriptors a process holds now.
fn descriptors(pid: i32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, Iterator::count)
}

#[test]
fn many_people_signed_in_share_the_web_processs_ports_and_each_gets_its_updates() {
    // 40 people, each in a tab holding a session of t1's two data services: more than
    // a process's default share of the broker (16 users), and each person a muster user
    // of its own, all driven by the web process's few worker threads through shared
    // ports to the broker and to t1 (each keeps only its inbox and bell).
    const PEOPLE: usize = 40;
    let users: Vec<(String, Vec<&str>)> = (0..PEOPLE)
        .map(|i| (format!("p{i}"), vec!["--web", "--allow", "t1/*"]))
        .collect();
    let w = setup_with("web-many", &users, &["--max-users-per-process", "64"], 32);
    let before = descriptors(w.pid);
    let mut tabs = Vec::new();
    for (i, (user, _)) in users.iter().enumerate() {
        let (cookie, csrf) = w.sign_in(user);
        let mut tab = w.socket(Some(&cookie), Some(&w.origin)).unwrap();
        let state = tab
            .until(Duration::from_secs(10), |f| f["t"] == "state")
            .unwrap_or_else(|| panic!("{user}'s tab got no state"));
        assert_eq!(state["user"], json!(user));
        assert_eq!(ids(&state), ["t1/s0", "t1/s1"], "{user} sees t1 only");
        let service = format!("t1/s{}", i % 2);
        tab.send(json!({"op": "request", "service": service}));
        tabs.push((user.clone(), service, tab, (cookie, csrf)));
    }
    // Every person's session is granted and streams: updates in order, none lost.
    for (user, service, tab, _) in &mut tabs {
        let granted = tab
            .until(Duration::from_secs(10), |f| f["t"] == "granted")
            .unwrap_or_else(|| panic!("{user}: no grant for {service}"));
        assert_eq!(granted["service"], json!(service));
        let session = granted["session"].clone();
        let mut seqs = Vec::new();
        while seqs.len() < 3 {
            let u = tab
                .until(Duration::from_secs(5), |f| {
                    f["t"] == "update" && f["session"] == session
                })
                .unwrap_or_else(|| panic!("{user}: {} updates of {service}", seqs.len()));
            seqs.push(u["seq"].as_u64().unwrap());
            assert_eq!(u["gap"], json!(0), "{user}: nothing lost");
        }
        assert!(
            seqs.windows(2).all(|p| p[1] == p[0] + 1),
            "{user}: updates in order, none missing: {seqs:?}"
        );
    }
    // The broker shows 40 sessions on t1 (20 on each service), every one a web user.
    let list = w.fed.list();
    for s in ["t1/s0", "t1/s1"] {
        let row = common::find(&list, s).unwrap();
        assert_eq!(row["in_use"], json!(PEOPLE / 2), "{s}: {row}");
    }
    // About 26 descriptors a person (a node, a thread and ports to the broker and t1
    // per person took about 48).
    let per_person = (descriptors(w.pid) - before) as f64 / PEOPLE as f64;
    assert!(
        per_person < 32.0,
        "{per_person:.1} descriptors per person signed in"
    );
    // Signing out ends every session: the counts fall back to 0.
    for (user, _, tab, (cookie, csrf)) in tabs {
        drop(tab);
        let a = http(
            w.port,
            "POST",
            "/api/logout",
            &[
                ("Origin", &w.origin),
                ("Cookie", &cookie),
                ("X-CSRF-Token", &csrf),
                ("Content-Type", "application/json"),
            ],
            "{}",
        );
        assert_eq!(a.status, 200, "{user} signs out: {}", a.body);
    }
    // (wait_list fails the test if they do not within the time.)
    w.fed.wait_list(Duration::from_secs(10), |l| {
        ["t1/s0", "t1/s1"]
            .iter()
            .all(|s| common::find(l, s).is_some_and(|r| r["in_use"] == json!(0)))
    });
}

#[test]
fn a_tab_outlives_a_broker_restart_and_nobody_can_sign_in_to_a_missing_broker() {
    let mut w = setup("web-restart");
    let (cookie, _) = w.sign_in("alice");
    let mut tab = w.socket(Some(&cookie), Some(&w.origin)).unwrap();
    let state = tab
        .until(Duration::from_secs(10), |f| f["t"] == "state")
        .unwrap();
    assert_eq!(state["broker_up"], json!(true));
    // The broker dies: the tab is told, and stays open.
    w.fed.proc(w.broker).signal(libc::SIGKILL);
    w.fed.proc(w.broker).wait(Duration::from_secs(5));
    let down = tab.until(Duration::from_secs(10), |f| f["t"] == "broker");
    assert_eq!(
        down.unwrap()["up"],
        json!(false),
        "the tab hears the broker is gone"
    );
    // Meanwhile a second person cannot get a connection: the socket is refused (503)
    // once `--wait` (2 s) has passed, and the first person's worker goes on.
    let (bob, _) = w.sign_in("bob");
    let started = Instant::now();
    assert_eq!(
        w.socket(Some(&bob), Some(&w.origin)).err(),
        Some(503),
        "no broker, no session"
    );
    assert!(
        started.elapsed() >= Duration::from_secs(2),
        "it waited for one"
    );
    // A new broker: the tab's user is welcomed again and its requests are served.
    w.broker = w.fed.broker(&[]);
    let up = tab.until(Duration::from_secs(15), |f| f["t"] == "broker");
    assert_eq!(
        up.unwrap()["up"],
        json!(true),
        "the tab hears the broker is back"
    );
    w.fed.wait_list(Duration::from_secs(15), |l| l.len() == 3);
    tab.send(json!({"op": "request", "service": "t1/s0"}));
    let granted = tab.until(Duration::from_secs(10), |f| {
        f["t"] == "granted" || f["t"] == "refused"
    });
    assert_eq!(granted.unwrap()["t"], json!("granted"));
    // And bob gets in now.
    let mut bobs = w.socket(Some(&bob), Some(&w.origin)).unwrap();
    let state = bobs
        .until(Duration::from_secs(10), |f| f["t"] == "state")
        .unwrap();
    assert_eq!(state["user"], json!("bob"));
}
