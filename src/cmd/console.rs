//! `muster console`: the operator's full-screen view (ratatui).
//!
//! It is a user of the broker like any other (it says hello, reads the shared-memory
//! list, and sends `Operate`), plus a reader of the broker's event feed. It redraws when
//! something changes: a key, a list change, an event, the answer to its status request
//! (asked after every event, and every few seconds for the systems' ping ages); idle,
//! it sleeps in the kernel.

use super::tui::{bold, clock, log_box, pane_table, service_row, Input, Inputs};
use crate::cli::ConsoleArgs;
use muster_shared::ipc::{create_node, EventReader};
use muster_shared::protocol::{BrokerStatus, EventRecord, Operation};
use muster_shared::snapshot::ServiceView;
use muster_shared::types::{ServiceId, UserId};
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserError, UserEvent, Wake};
use ratatui::crossterm::event::KeyCode;
use ratatui::layout::{Constraint, Layout};
use ratatui::text::Line;
use ratatui::widgets::{Block, Borders, Paragraph, Row, Table};
use ratatui::Frame;
use std::collections::{HashMap, VecDeque};
use std::io::Write;
use std::process::ExitCode;
use std::time::{Duration, Instant};

/// The status is read again this often when nothing happens (ping ages move on).
const STATUS_EVERY: Duration = Duration::from_secs(3);
/// Event lines kept.
const LOG_LINES: usize = 500;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Pane {
    Services,
    Sessions,
    Users,
    Queues,
}

impl Pane {
    fn next(self) -> Self {
        match self {
            Pane::Services => Pane::Sessions,
            Pane::Sessions => Pane::Users,
            Pane::Users => Pane::Queues,
            Pane::Queues => Pane::Services,
        }
    }
}

struct Console {
    /// Where the console looks from: the instance, or the remote broker's address.
    place: String,
    list: Vec<ServiceView>,
    status: BrokerStatus,
    log: VecDeque<String>,
    pane: Pane,
    sel: [usize; 4],
    message: String,
    asked: Option<u64>,
    last_status: Instant,
    /// The last event record's broker run and number.
    last_record: Option<(String, u64)>,
    /// Messages a second per kind, from the counts of the last two statuses.
    rates: HashMap<String, f64>,
    /// When the last status came, and its counts per kind.
    counted: Option<(Instant, HashMap<String, u64>)>,
}

fn index(p: Pane) -> usize {
    p as usize
}

/// One event as a log line.
fn describe(r: &EventRecord) -> String {
    let v = serde_json::to_value(&r.event).unwrap_or_default();
    let kind = v["event"].as_str().unwrap_or("?").to_string();
    let mut fields: Vec<String> = v
        .as_object()
        .map(|o| {
            o.iter()
                .filter(|(k, _)| k.as_str() != "event")
                .map(|(k, x)| match x {
                    serde_json::Value::String(s) => format!("{k}={s}"),
                    other => format!("{k}={other}"),
                })
                .collect()
        })
        .unwrap_or_default();
    fields.sort();
    format!(
        "{} {kind} {}",
        clock(r.t_ns / 1_000_000_000),
        fields.join(" ")
    )
}

impl Console {
    /// A record of the event feed, into the log; a jump in its numbers says how many
    /// were missed (a remote operator's feed is best effort).
    fn took_record(&mut self, r: &EventRecord) {
        if let Some((epoch, seq)) = &self.last_record {
            if *epoch == r.epoch && r.seq > seq + 1 {
                self.log
                    .push_back(format!("({} events missed)", r.seq - seq - 1));
            }
        }
        self.last_record = Some((r.epoch.clone(), r.seq));
        self.log.push_back(describe(r));
        while self.log.len() > LOG_LINES {
            self.log.pop_front();
        }
    }

    /// Something happened at the broker: the status again, at once.
    fn status_soon(&mut self) {
        if self.asked.is_none() {
            self.last_status = Instant::now()
                .checked_sub(STATUS_EVERY)
                .unwrap_or(self.last_status);
        }
    }

    /// Takes a new status in, and the message rates since the one before.
    fn took_status(&mut self, s: BrokerStatus) {
        let now = Instant::now();
        let counts: HashMap<String, u64> = s
            .handling
            .iter()
            .map(|h| (h.kind.clone(), h.count))
            .collect();
        // A new broker run (a takeover, a restart) counts from zero again.
        if let Some((then, before)) = self
            .counted
            .as_ref()
            .filter(|_| s.epoch == self.status.epoch)
        {
            let dt = now.duration_since(*then).as_secs_f64();
            if dt > 0.0 {
                self.rates = counts
                    .iter()
                    .map(|(k, n)| {
                        let was = before.get(k).copied().unwrap_or(0);
                        (k.clone(), n.saturating_sub(was) as f64 / dt)
                    })
                    .collect();
            }
        } else {
            self.rates.clear();
        }
        self.counted = Some((now, counts));
        self.status = s;
    }

    /// The queued requests, flattened in display order: (service, user, req, place).
    fn queued(&self) -> Vec<(ServiceId, UserId, u64, usize)> {
        self.status
            .queues
            .iter()
            .flat_map(|q| {
                q.waiting
                    .iter()
                    .enumerate()
                    .map(|(i, (u, r))| (q.service.clone(), u.clone(), *r, i + 1))
            })
            .collect()
    }

    fn rows(&self, p: Pane) -> usize {
        match p {
            Pane::Services => self.list.len(),
            Pane::Sessions => self.status.sessions.len(),
            Pane::Users => self.status.users.len(),
            Pane::Queues => self.queued().len(),
        }
    }

    fn clamp(&mut self) {
        for p in [Pane::Services, Pane::Sessions, Pane::Users, Pane::Queues] {
            let n = self.rows(p);
            let s = &mut self.sel[index(p)];
            *s = (*s).min(n.saturating_sub(1));
        }
    }

    /// The action a key asks for on the selected row, if any.
    fn action(&self, key: KeyCode) -> Option<Operation> {
        let sel = self.sel[index(self.pane)];
        match (self.pane, key) {
            (Pane::Services, KeyCode::Char('w')) => {
                self.list.get(sel).map(|v| Operation::Withdraw {
                    service: ServiceId(v.id.clone()),
                })
            }
            (Pane::Services, KeyCode::Char('r')) => {
                self.list.get(sel).map(|v| Operation::Restore {
                    service: ServiceId(v.id.clone()),
                })
            }
            (Pane::Sessions, KeyCode::Char('e')) => self
                .status
                .sessions
                .get(sel)
                .map(|s| Operation::EndSession { session: s.session }),
            (Pane::Users, KeyCode::Char('d')) => {
                self.status.users.get(sel).map(|u| Operation::DropUser {
                    user: u.user.clone(),
                })
            }
            (Pane::Queues, KeyCode::Char(c @ ('+' | '-'))) => {
                self.queued().get(sel).map(|(service, user, req, place)| {
                    let position = if c == '+' {
                        place.saturating_sub(1).max(1)
                    } else {
                        place + 1
                    };
                    Operation::MoveRequest {
                        service: service.clone(),
                        user: user.clone(),
                        req: *req,
                        position: u16::try_from(position).unwrap_or(u16::MAX),
                    }
                })
            }
            (Pane::Queues, KeyCode::Char('x')) => {
                self.queued()
                    .get(sel)
                    .map(|(service, user, req, _)| Operation::DropRequest {
                        service: service.clone(),
                        user: user.clone(),
                        req: *req,
                    })
            }
            _ => None,
        }
    }

    fn draw(&self, f: &mut Frame) {
        let [top, middle, log, help] = Layout::vertical([
            Constraint::Length(2),
            Constraint::Min(10),
            Constraint::Length(9),
            Constraint::Length(1),
        ])
        .areas(f.area());
        let s = &self.status;
        let title = format!(
            "muster console: {}, broker run {:016x}: {} services, {} systems, {} users, {} sessions",
            self.place,
            s.epoch,
            self.list.len(),
            s.systems.len(),
            s.users_total,
            s.sessions_total
        );
        f.render_widget(
            Paragraph::new(vec![Line::from(title), Line::from(self.message.clone())]),
            top,
        );
        let [left, right] =
            Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
                .areas(middle);
        let [services_area, systems_area, figures_area] = Layout::vertical([
            Constraint::Percentage(45),
            Constraint::Percentage(25),
            Constraint::Percentage(30),
        ])
        .areas(left);
        let [sessions_area, users_area, queues_area] = Layout::vertical([
            Constraint::Percentage(40),
            Constraint::Percentage(30),
            Constraint::Percentage(30),
        ])
        .areas(right);
        let services = self.list.iter().map(|v| service_row(v, false));
        pane_table(
            f,
            services_area,
            "services (w withdraw, r restore)",
            self.focus(Pane::Services),
            &["id", "kind", "in use", "queued", "links", ""],
            &[25, 8, 7, 6, 5, 20],
            services.collect(),
        );
        let systems = s.systems.iter().map(|x| {
            Row::new(vec![
                x.name.clone(),
                x.pid.to_string(),
                x.sessions.to_string(),
                x.last_answer_ms
                    .map_or("never".into(), |ms| format!("{:.1} s", ms as f64 / 1000.0)),
                x.delinquencies.to_string(),
            ])
        });
        let t = Table::new(
            systems.collect::<Vec<_>>(),
            [16, 8, 8, 14, 11].map(Constraint::Length),
        )
        .header(Row::new(["system", "pid", "sessions", "last answer", "delinquent"]).style(bold()))
        .block(Block::default().borders(Borders::ALL).title("systems"));
        f.render_widget(t, systems_area);
        // The broker's handling: the busiest kinds first.
        let mut kinds: Vec<_> = s.handling.iter().collect();
        kinds.sort_by(|a, b| b.count.cmp(&a.count).then(a.kind.cmp(&b.kind)));
        let total: f64 = self.rates.values().sum();
        let figures = kinds.iter().map(|h| {
            Row::new(vec![
                h.kind.clone(),
                h.count.to_string(),
                self.rates
                    .get(&h.kind)
                    .map_or("-".into(), |r| format!("{r:.1}")),
                h.p50_us.to_string(),
                h.p99_us.to_string(),
                h.max_us.to_string(),
            ])
        });
        let t = Table::new(
            figures.collect::<Vec<_>>(),
            [14, 9, 8, 7, 7, 8].map(Constraint::Length),
        )
        .header(Row::new(["handled", "count", "per s", "p50 µs", "p99 µs", "max µs"]).style(bold()))
        .block(
            Block::default()
                .borders(Borders::ALL)
                .title(format!("broker figures: {total:.1} messages/s")),
        );
        f.render_widget(t, figures_area);
        let sessions = s.sessions.iter().map(|x| {
            Row::new(vec![
                format!("{:016x}", x.session.0),
                x.service.0.clone(),
                x.user.0.clone(),
            ])
        });
        pane_table(
            f,
            sessions_area,
            "sessions (e end)",
            self.focus(Pane::Sessions),
            &["session", "service", "user", "", "", ""],
            &[17, 20, 24, 0, 0, 0],
            sessions.collect(),
        );
        let users = s.users.iter().map(|u| {
            Row::new(vec![
                u.user.0.clone(),
                if u.pid == 0 {
                    "remote".into()
                } else {
                    u.pid.to_string()
                },
                u.links.len().to_string(),
            ])
        });
        pane_table(
            f,
            users_area,
            "users (d drop)",
            self.focus(Pane::Users),
            &["user", "pid", "links", "", "", ""],
            &[26, 8, 5, 0, 0, 0],
            users.collect(),
        );
        let queued = self
            .queued()
            .into_iter()
            .map(|(service, user, req, place)| {
                Row::new(vec![service.0, place.to_string(), user.0, req.to_string()])
            });
        pane_table(
            f,
            queues_area,
            "task queues (+ up, - down, x drop)",
            self.focus(Pane::Queues),
            &["service", "place", "user", "request", "", ""],
            &[20, 5, 24, 7, 0, 0],
            queued.collect(),
        );
        log_box(f, log, "events", self.log.iter());
        f.render_widget(
            Paragraph::new("Tab: next pane  Up/Down: select  q: quit"),
            help,
        );
    }

    /// The selected row of a pane, if it has the focus.
    fn focus(&self, pane: Pane) -> Option<usize> {
        (self.pane == pane).then(|| self.sel[index(pane)])
    }
}

/// `muster console`.
pub fn run(inst: &Instance, a: ConsoleArgs) -> anyhow::Result<ExitCode> {
    let opts = ConnectOptions {
        wait_for_broker: a.wait,
        handle_signals: true,
        watch_list: true,
    };
    let mut client = super::user::connect(inst, &a.remote, &opts)?;
    let part = a.list.part();
    client.watch_part(Some(part.filter.clone()))?;
    let inputs = Inputs::start(&mut client)?;
    // A remote operator hears the event feed from the broker's front (once it has
    // acted: the first status read); a local one reads the feed in shared memory.
    let remote = a.remote.remote;
    if remote.is_none() {
        let ((tx, mut bell), inst) = (inputs.sender()?, inst.clone());
        std::thread::spawn(move || {
            let Ok(node) = create_node("muster-console-feed", false) else {
                return;
            };
            let mut feed = None;
            loop {
                if feed.is_none() {
                    feed = EventReader::open(&node, &inst).ok();
                }
                let Some(f) = feed.as_mut() else {
                    std::thread::sleep(Duration::from_secs(1));
                    continue;
                };
                while let Some(r) = f.next_event() {
                    if tx.send(Input::Feed(r)).is_err() {
                        return;
                    }
                }
                if bell.write_all(&[2]).is_err() {
                    return;
                }
                f.wait(Duration::from_secs(3600));
            }
        });
    }
    let mut c = Console {
        place: match remote {
            Some(addr) => format!("{} via {addr}", client.id()),
            None => format!("instance {inst}"),
        },
        list: Vec::new(),
        status: BrokerStatus::default(),
        log: VecDeque::new(),
        pane: Pane::Services,
        sel: [0; 4],
        message: String::new(),
        asked: None,
        last_status: Instant::now()
            .checked_sub(STATUS_EVERY)
            .unwrap_or_else(Instant::now),
        rates: HashMap::new(),
        counted: None,
        last_record: None,
    };
    let mut terminal = ratatui::init();
    let outcome = (|| -> anyhow::Result<()> {
        let mut dirty = true;
        let mut list_owed = true;
        loop {
            if list_owed {
                c.list = client.list_part(&part)?.views();
                list_owed = false;
                dirty = true;
            }
            if c.asked.is_none() && c.last_status.elapsed() >= STATUS_EVERY {
                c.asked = Some(client.operate(Operation::Status));
                c.last_status = Instant::now();
            }
            if dirty {
                c.clamp();
                terminal.draw(|f| c.draw(f))?;
                dirty = false;
            }
            let deadline = c.last_status + STATUS_EVERY;
            match client.wait(deadline) {
                Ok(Wake::Event(UserEvent::Operated { id, result })) => {
                    if c.asked == Some(id) {
                        c.asked = None;
                        match result {
                            Ok(Some(s)) => c.took_status(*s),
                            Ok(None) => {}
                            Err(e) => c.message = format!("status: {e}"),
                        }
                    } else {
                        c.message = match result {
                            Ok(_) => "done".into(),
                            Err(e) => format!("refused: {e}"),
                        };
                    }
                    dirty = true;
                }
                Ok(Wake::Event(UserEvent::ListChanged | UserEvent::Connected { .. })) => {
                    list_owed = true;
                }
                Ok(Wake::Event(UserEvent::BrokerLost)) => {
                    c.message = "broker lost: waiting for one".into();
                    dirty = true;
                }
                Ok(Wake::Event(UserEvent::Feed(r))) => {
                    c.took_record(&r);
                    c.status_soon();
                    dirty = true;
                }
                Ok(Wake::Event(_)) => {}
                Ok(Wake::Timeout) => {}
                Ok(Wake::Extra) => {
                    let mut changed = false;
                    for input in inputs.drain() {
                        if input.is_quit() {
                            return Ok(());
                        }
                        match input {
                            Input::Key(KeyCode::Tab, _) => c.pane = c.pane.next(),
                            Input::Key(KeyCode::Down, _) => {
                                let s = &mut c.sel[index(c.pane)];
                                *s = s.saturating_add(1);
                            }
                            Input::Key(KeyCode::Up, _) => {
                                let s = &mut c.sel[index(c.pane)];
                                *s = s.saturating_sub(1);
                            }
                            Input::Key(k, _) => {
                                if let Some(op) = c.action(k) {
                                    c.message = format!("{op}...");
                                    client.operate(op);
                                }
                            }
                            Input::Resize => {}
                            Input::Feed(r) => {
                                c.took_record(&r);
                                changed = true;
                            }
                        }
                        dirty = true;
                    }
                    if changed {
                        c.status_soon();
                    }
                }
                Err(UserError::Interrupted) => return Ok(()),
                Err(e) => return Err(e.into()),
            }
        }
    })();
    ratatui::restore();
    client.close();
    outcome?;
    Ok(ExitCode::SUCCESS)
}
