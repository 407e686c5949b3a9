//! `muster user` on a terminal: the user's full-screen view (ratatui).
//!
//! The service list (read again whenever the broker says it changed), the user's
//! sessions and waiting requests, its links, the selected session's updates as they
//! come, and a log of what the broker and the systems said. Keys request, end, link,
//! send a goal and cancel; the numbered menu (`muster_users::menu`) stays for pipes and
//! dumb terminals (`--plain`).

use super::tui::{clock, log_box, pane_table, service_row, Input, Inputs};
use muster_shared::snapshot::ServiceView;
use muster_shared::types::{Payload, ServiceId, ServiceKind, SessionId};
use muster_users::{UserClient, UserError, UserEvent, Wake};
use ratatui::crossterm::event::KeyCode;
use ratatui::layout::{Constraint, Layout};
use ratatui::text::Line;
use ratatui::widgets::{Paragraph, Row};
use ratatui::Frame;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Log lines kept, and updates kept per session.
const LOG_LINES: usize = 300;
const RECENT: usize = 200;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Pane {
    Services,
    Sessions,
    Links,
}

/// A row of the sessions pane: a granted session, or a request still waiting.
enum Held {
    Session {
        id: SessionId,
        service: ServiceId,
        kind: ServiceKind,
        updates: u64,
        last_seq: u64,
        gaps: u64,
        /// The latest update or status, and the ones before it (newest last).
        recent: VecDeque<String>,
    },
    Waiting {
        req: u64,
        service: ServiceId,
        /// Place in the task queue, once the broker said.
        position: Option<u16>,
    },
}

struct LinkRow {
    link: u64,
    data: ServiceId,
    command: ServiceId,
    up: bool,
    forwarded: u64,
    last: String,
}

/// What the keys do at the moment.
enum Mode {
    Normal,
    /// Typing a goal `X Y` for a command session.
    Goal {
        session: SessionId,
        text: String,
    },
    /// A data service is chosen; the next Enter (or `l`) on a service links it there.
    LinkFrom(ServiceId),
}

struct View {
    who: String,
    list: Vec<ServiceView>,
    held: Vec<Held>,
    links: Vec<LinkRow>,
    log: VecDeque<String>,
    pane: Pane,
    sel: [usize; 3],
    mode: Mode,
    message: String,
    connected: bool,
}

impl View {
    fn note(&mut self, line: String) {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        self.log.push_back(format!("{} {line}", clock(now)));
        while self.log.len() > LOG_LINES {
            self.log.pop_front();
        }
    }

    fn rows(&self, p: Pane) -> usize {
        match p {
            Pane::Services => self.list.len(),
            Pane::Sessions => self.held.len(),
            Pane::Links => self.links.len(),
        }
    }

    fn clamp(&mut self) {
        for p in [Pane::Services, Pane::Sessions, Pane::Links] {
            let n = self.rows(p);
            let s = &mut self.sel[p as usize];
            *s = (*s).min(n.saturating_sub(1));
        }
    }

    fn focus(&self, p: Pane) -> Option<usize> {
        (self.pane == p).then(|| self.sel[p as usize])
    }

    fn selected_service(&self) -> Option<&ServiceView> {
        self.list.get(self.sel[Pane::Services as usize])
    }

    fn session_mut(&mut self, session: SessionId) -> Option<&mut Held> {
        self.held
            .iter_mut()
            .find(|h| matches!(h, Held::Session { id, .. } if *id == session))
    }

    /// Takes in what the client heard.
    fn event(&mut self, e: UserEvent) {
        match e {
            UserEvent::Connected { epoch } => {
                self.connected = true;
                self.note(format!("connected to a broker (run {epoch:016x})"));
            }
            UserEvent::BrokerLost => {
                self.connected = false;
                self.note("broker lost: sessions go on; new requests wait".into());
            }
            UserEvent::ListChanged => {}
            UserEvent::Queued {
                req,
                service,
                position,
            } => {
                self.note(format!("{service}: queued at position {position}"));
                for h in &mut self.held {
                    if let Held::Waiting {
                        req: r,
                        position: p,
                        ..
                    } = h
                    {
                        if *r == req {
                            *p = Some(position);
                        }
                    }
                }
            }
            UserEvent::Granted {
                req,
                session,
                service,
                kind,
                ..
            } => {
                self.note(format!("granted {service}: session {session} ({kind})"));
                self.held
                    .retain(|h| !matches!(h, Held::Waiting { req: r, .. } if *r == req));
                self.held.push(Held::Session {
                    id: session,
                    service,
                    kind,
                    updates: 0,
                    last_seq: 0,
                    gaps: 0,
                    recent: VecDeque::new(),
                });
            }
            UserEvent::Refused {
                req,
                service,
                reason,
            } => {
                self.note(format!("refused {service}: {reason}"));
                self.held
                    .retain(|h| !matches!(h, Held::Waiting { req: r, .. } if *r == req));
            }
            UserEvent::Update {
                session,
                seq,
                gap,
                payload,
                ..
            } => self.took(session, seq, gap, format!("#{seq} {payload}")),
            UserEvent::Status {
                session,
                seq,
                status,
                ..
            } => self.took(session, seq, 0, format!("#{seq} {status}")),
            UserEvent::Ended {
                session,
                service,
                reason,
                lost_at_end,
            } => {
                let lost = match lost_at_end {
                    0 => String::new(),
                    n => format!(" (its last {n} never came)"),
                };
                self.note(format!(
                    "session {session} on {service} ended: {reason}{lost}"
                ));
                self.held
                    .retain(|h| !matches!(h, Held::Session { id, .. } if *id == session));
            }
            UserEvent::EndConfirmed { .. } | UserEvent::Operated { .. } | UserEvent::Feed(_) => {}
            UserEvent::LinkUp { link } => {
                self.note(format!("link {link} up"));
                if let Some(l) = self.links.iter_mut().find(|l| l.link == link) {
                    l.up = true;
                }
            }
            UserEvent::LinkForwarded { link, input } => {
                if let Some(l) = self.links.iter_mut().find(|l| l.link == link) {
                    l.forwarded += 1;
                    l.last = input.to_string();
                }
            }
            UserEvent::LinkEnded { link, reason } => {
                self.note(format!("link {link} ended: {reason}"));
                self.links.retain(|l| l.link != link);
            }
        }
    }

    fn took(&mut self, session: SessionId, seq: u64, gap: u64, line: String) {
        if let Some(Held::Session {
            updates,
            last_seq,
            gaps,
            recent,
            ..
        }) = self.session_mut(session)
        {
            *updates += 1;
            *last_seq = seq;
            *gaps += gap;
            recent.push_back(line);
            while recent.len() > RECENT {
                recent.pop_front();
            }
        }
    }

    /// Acts on a key; `false` quits.
    fn key(&mut self, client: &mut UserClient, input: &Input) -> Result<bool, UserError> {
        let Input::Key(code, _) = input else {
            return Ok(true);
        };
        // Typing a goal: the keys are the text.
        if let Mode::Goal { session, text } = &mut self.mode {
            match code {
                KeyCode::Char(c) if c.is_ascii_digit() || matches!(c, '.' | '-' | ' ' | ',') => {
                    text.push(*c)
                }
                KeyCode::Backspace => {
                    text.pop();
                }
                KeyCode::Enter => {
                    let (session, text) = (*session, text.clone());
                    self.mode = Mode::Normal;
                    self.message = match parse_xy(&text) {
                        Some((x, y)) => match client.input(session, Payload::Goal2d { x, y }) {
                            Ok(()) => format!("goal ({x}, {y}) sent"),
                            Err(e) => e,
                        },
                        None => format!("not a goal: {text:?} (X Y in metres)"),
                    };
                }
                KeyCode::Esc => {
                    self.mode = Mode::Normal;
                    self.message.clear();
                }
                _ => {}
            }
            return Ok(true);
        }
        if input.is_quit() {
            if matches!(self.mode, Mode::LinkFrom(_)) && *code == KeyCode::Esc {
                self.mode = Mode::Normal;
                self.message = "link cancelled".into();
                return Ok(true);
            }
            return Ok(false);
        }
        let sel = self.sel[self.pane as usize];
        match (self.pane, code) {
            (_, KeyCode::Tab) => {
                self.pane = match self.pane {
                    Pane::Services => Pane::Sessions,
                    Pane::Sessions => Pane::Links,
                    Pane::Links => Pane::Services,
                }
            }
            (p, KeyCode::Down) => {
                let s = &mut self.sel[p as usize];
                *s = s.saturating_add(1);
            }
            (p, KeyCode::Up) => {
                let s = &mut self.sel[p as usize];
                *s = s.saturating_sub(1);
            }
            (Pane::Services, KeyCode::Enter | KeyCode::Char('r' | 'l')) => {
                let Some(v) = self.selected_service() else {
                    return Ok(true);
                };
                let id = ServiceId(v.id.clone());
                let is_data = v.kind == ServiceKind::Data.to_string();
                match (std::mem::replace(&mut self.mode, Mode::Normal), code) {
                    (Mode::LinkFrom(data), KeyCode::Enter | KeyCode::Char('l')) => {
                        self.message = match client.link(&data, &id) {
                            Ok(link) => {
                                self.links.push(LinkRow {
                                    link,
                                    data: data.clone(),
                                    command: id.clone(),
                                    up: false,
                                    forwarded: 0,
                                    last: String::new(),
                                });
                                format!("linking {data} -> {id} (link {link})")
                            }
                            Err(e) => format!("link: {e}"),
                        };
                    }
                    (_, KeyCode::Char('l')) if is_data => {
                        self.message = format!(
                            "link {id} into: select a command service, Enter (Esc cancels)"
                        );
                        self.mode = Mode::LinkFrom(id);
                    }
                    (_, KeyCode::Char('l')) => {
                        self.message = "a link starts at a data service".into();
                    }
                    _ => {
                        let req = client.request(&id)?;
                        self.held.push(Held::Waiting {
                            req,
                            service: id.clone(),
                            position: None,
                        });
                        self.message = format!("requested {id}");
                    }
                }
            }
            (Pane::Sessions, KeyCode::Char('e')) => match self.held.get(sel) {
                Some(Held::Session { id, service, .. }) => {
                    self.message = format!("ending the session on {service}");
                    client.end(*id);
                }
                Some(Held::Waiting { req, service, .. }) => {
                    self.message = format!("request for {service} cancelled");
                    client.cancel(*req);
                    self.held.remove(sel);
                }
                None => {}
            },
            (Pane::Sessions, KeyCode::Char('g')) => match self.held.get(sel) {
                Some(Held::Session {
                    id,
                    kind: ServiceKind::Command,
                    ..
                }) => {
                    self.message = "goal X Y (metres), Enter sends, Esc cancels: ".into();
                    self.mode = Mode::Goal {
                        session: *id,
                        text: String::new(),
                    };
                }
                _ => self.message = "a goal goes to a command session".into(),
            },
            (Pane::Links, KeyCode::Char('e')) => {
                if let Some(l) = self.links.get(sel) {
                    self.message = format!("ending link {}", l.link);
                    client.unlink(l.link);
                }
            }
            _ => {}
        }
        Ok(true)
    }

    fn draw(&self, f: &mut Frame) {
        let [top, middle, log, help] = Layout::vertical([
            Constraint::Length(2),
            Constraint::Min(10),
            Constraint::Length(8),
            Constraint::Length(1),
        ])
        .areas(f.area());
        let sessions = self
            .held
            .iter()
            .filter(|h| matches!(h, Held::Session { .. }))
            .count();
        let title = format!(
            "muster user {}{}: {} services, {} sessions, {} links",
            self.who,
            if self.connected { "" } else { " (no broker)" },
            self.list.len(),
            sessions,
            self.links.len()
        );
        let message = match &self.mode {
            Mode::Goal { text, .. } => format!("{}{text}_", self.message),
            _ => self.message.clone(),
        };
        f.render_widget(
            Paragraph::new(vec![Line::from(title), Line::from(message)]),
            top,
        );
        let [left, right] =
            Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
                .areas(middle);
        let services = self.list.iter().map(|v| service_row(v, true));
        pane_table(
            f,
            left,
            "services (Enter request, l link)",
            self.focus(Pane::Services),
            &["id", "kind", "payload", "in use", "queued", "links", ""],
            &[22, 8, 8, 7, 6, 5, 16],
            services.collect(),
        );
        let [sessions_area, links_area, updates_area] = Layout::vertical([
            Constraint::Percentage(35),
            Constraint::Percentage(25),
            Constraint::Percentage(40),
        ])
        .areas(right);
        let held = self.held.iter().map(|h| match h {
            Held::Session {
                id,
                service,
                kind,
                updates,
                last_seq,
                gaps,
                ..
            } => Row::new(vec![
                id.to_string(),
                service.0.clone(),
                kind.to_string(),
                updates.to_string(),
                last_seq.to_string(),
                gaps.to_string(),
            ]),
            Held::Waiting {
                service, position, ..
            } => Row::new(vec![
                match position {
                    Some(p) => format!("queued, place {p}"),
                    None => "asked".into(),
                },
                service.0.clone(),
                String::new(),
                String::new(),
                String::new(),
                String::new(),
            ]),
        });
        pane_table(
            f,
            sessions_area,
            "sessions (e end, g goal)",
            self.focus(Pane::Sessions),
            &["session", "service", "kind", "updates", "seq", "gaps"],
            &[17, 20, 8, 7, 7, 5],
            held.collect(),
        );
        let links = self.links.iter().map(|l| {
            Row::new(vec![
                l.link.to_string(),
                format!("{} -> {}", l.data, l.command),
                if l.up { "up" } else { "starting" }.to_string(),
                l.forwarded.to_string(),
                l.last.clone(),
            ])
        });
        pane_table(
            f,
            links_area,
            "links (e end)",
            self.focus(Pane::Links),
            &["link", "data -> command", "state", "fwd", "last input"],
            &[4, 26, 8, 5, 26],
            links.collect(),
        );
        // The updates of the session selected in the sessions pane.
        let (title, recent) = match self.held.get(self.sel[Pane::Sessions as usize]) {
            Some(Held::Session {
                service, recent, ..
            }) => (format!("updates of {service}"), Some(recent)),
            _ => ("updates (select a session)".to_string(), None),
        };
        log_box(f, updates_area, &title, recent.into_iter().flatten());
        log_box(f, log, "log", self.log.iter());
        f.render_widget(
            Paragraph::new("Tab: next pane  Up/Down: select  q: quit"),
            help,
        );
    }
}

/// `X Y` or `X,Y` in metres.
fn parse_xy(s: &str) -> Option<(f64, f64)> {
    let mut it = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|w| !w.is_empty())
        .map(str::parse::<f64>);
    match (it.next(), it.next(), it.next()) {
        (Some(Ok(x)), Some(Ok(y)), None) if x.is_finite() && y.is_finite() => Some((x, y)),
        _ => None,
    }
}

/// Runs the full-screen view until `q`, Ctrl-C or a signal.
pub fn run(
    mut client: UserClient,
    who: String,
    part: &muster_shared::snapshot::ListPart,
) -> anyhow::Result<()> {
    let inputs = Inputs::start(&mut client)?;
    let mut v = View {
        who,
        list: Vec::new(),
        held: Vec::new(),
        links: Vec::new(),
        log: VecDeque::new(),
        pane: Pane::Services,
        sel: [0; 3],
        mode: Mode::Normal,
        message: String::new(),
        connected: client.core().connected().is_some(),
    };
    let mut terminal = ratatui::init();
    let outcome = (|| -> anyhow::Result<()> {
        let mut dirty = true;
        let mut list_owed = true;
        loop {
            if list_owed {
                v.list = client.list_part(part)?.views();
                list_owed = false;
                dirty = true;
            }
            if dirty {
                v.clamp();
                terminal.draw(|f| v.draw(f))?;
                dirty = false;
            }
            // Sleep until something happens; then take every event already here before
            // the next redraw, and the keys every time: a stream of updates must neither
            // redraw once per update nor keep the keys waiting.
            let mut deadline = Instant::now() + Duration::from_secs(3600);
            loop {
                match client.wait(deadline) {
                    Ok(Wake::Event(e)) => {
                        list_owed |=
                            matches!(e, UserEvent::ListChanged | UserEvent::Connected { .. });
                        v.event(e);
                        dirty = true;
                        deadline = Instant::now();
                    }
                    Ok(Wake::Timeout | Wake::Extra) => break,
                    Err(UserError::Interrupted) => return Ok(()),
                    Err(e) => return Err(e.into()),
                }
            }
            for input in inputs.drain() {
                if !v.key(&mut client, &input)? {
                    return Ok(());
                }
                dirty = true;
            }
        }
    })();
    ratatui::restore();
    client.close();
    outcome
}

#[cfg(test)]
mod tests {
    use super::parse_xy;

    #[test]
    fn goals_are_two_finite_numbers() {
        assert_eq!(parse_xy("3 4.5"), Some((3.0, 4.5)));
        assert_eq!(parse_xy(" -1,2 "), Some((-1.0, 2.0)));
        assert_eq!(parse_xy("3"), None);
        assert_eq!(parse_xy("1 2 3"), None);
        assert_eq!(parse_xy("1e999 2"), None);
        assert_eq!(parse_xy(""), None);
    }
}
