//! What the two full-screen views (`muster console` and `muster user`) share: the
//! thread that reads keys, the bell that wakes the client's reactor when input comes,
//! and a bordered table with a selected row.
//!
//! Both views redraw on change only: the client's reactor sleeps in the kernel until a
//! message, a list change or the bell, so an idle view costs no CPU.

use anyhow::Context;
use muster_shared::protocol::EventRecord;
use muster_shared::snapshot::ServiceView;
use muster_users::UserClient;
use ratatui::crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
use ratatui::layout::{Constraint, Rect};
use ratatui::style::{Modifier, Style};
use ratatui::text::Line;
use ratatui::widgets::{Block, Borders, Paragraph, Row, Table, TableState};
use ratatui::Frame;
use std::io::{IsTerminal, Read, Write};
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::sync::mpsc;

/// What the helper threads hand a view.
pub enum Input {
    /// A key was pressed.
    Key(KeyCode, KeyModifiers),
    /// The terminal changed size.
    Resize,
    /// A record of the broker's event feed (the console's second helper).
    Feed(EventRecord),
}

impl Input {
    /// `q`, Esc or Ctrl-C.
    pub fn is_quit(&self) -> bool {
        match self {
            Input::Key(KeyCode::Char('q') | KeyCode::Esc, _) => true,
            Input::Key(KeyCode::Char('c'), m) => m.contains(KeyModifiers::CONTROL),
            _ => false,
        }
    }
}

/// The inputs of a view: a channel the helpers send on, and a socket pair whose
/// reading end the client's reactor watches ([`muster_users::Wake::Extra`]).
pub struct Inputs {
    tx: mpsc::Sender<Input>,
    rx: mpsc::Receiver<Input>,
    bell_rx: UnixStream,
    bell_tx: UnixStream,
}

impl Inputs {
    /// Starts the key reader and makes `client` wake on every input.
    pub fn start(client: &mut UserClient) -> anyhow::Result<Self> {
        let (bell_rx, bell_tx) = UnixStream::pair().context("a socket pair")?;
        bell_rx.set_nonblocking(true)?;
        client.watch_extra(bell_rx.as_raw_fd())?;
        let (tx, rx) = mpsc::channel();
        let inputs = Inputs {
            tx,
            rx,
            bell_rx,
            bell_tx,
        };
        let (tx, mut bell) = inputs.sender()?;
        std::thread::spawn(move || {
            while let Ok(ev) = event::read() {
                let input = match ev {
                    Event::Key(k) if k.kind == KeyEventKind::Press => {
                        Input::Key(k.code, k.modifiers)
                    }
                    Event::Resize(..) => Input::Resize,
                    _ => continue,
                };
                if tx.send(input).is_err() || bell.write_all(&[1]).is_err() {
                    return;
                }
            }
        });
        Ok(inputs)
    }

    /// A sender and a bell for another helper thread: send, then ring.
    pub fn sender(&self) -> anyhow::Result<(mpsc::Sender<Input>, UnixStream)> {
        Ok((self.tx.clone(), self.bell_tx.try_clone()?))
    }

    /// Everything that came since the last call (call it on `Wake::Extra`).
    pub fn drain(&self) -> Vec<Input> {
        let mut buf = [0u8; 256];
        while matches!((&self.bell_rx).read(&mut buf), Ok(n) if n > 0) {}
        self.rx.try_iter().collect()
    }
}

/// Whether a full-screen view can run: standard input and output are terminals, and
/// the terminal is not a dumb one.
pub fn interactive() -> bool {
    std::io::stdin().is_terminal()
        && std::io::stdout().is_terminal()
        && std::env::var("TERM").is_ok_and(|t| !t.is_empty() && t != "dumb")
}

/// The time of day (UTC) of Unix time `secs`, `hh:mm:ss`, for log lines.
pub fn clock(secs: u64) -> String {
    format!(
        "{:02}:{:02}:{:02}",
        (secs / 3600) % 24,
        (secs / 60) % 60,
        secs % 60
    )
}

pub fn bold() -> Style {
    Style::default().add_modifier(Modifier::BOLD)
}

/// A bordered table; the selected row is shown reversed when the pane has the focus
/// (its title then in brackets).
pub fn pane_table(
    f: &mut Frame,
    area: Rect,
    title: &str,
    selected: Option<usize>,
    header: &[&str],
    widths: &[u16],
    rows: Vec<Row>,
) {
    let title = match selected {
        Some(_) => format!("[{title}]"),
        None => title.to_string(),
    };
    let t = Table::new(rows, widths.iter().map(|w| Constraint::Length(*w)))
        .header(Row::new(header.to_vec()).style(bold()))
        .block(Block::default().borders(Borders::ALL).title(title))
        .row_highlight_style(Style::default().add_modifier(Modifier::REVERSED));
    let mut state = TableState::default();
    state.select(selected);
    f.render_stateful_widget(t, area, &mut state);
}

/// A service as a table row: id, kind, (payload,) in use / quota, queued, links, and
/// what else to know (withdrawn, its host).
pub fn service_row(v: &ServiceView, payload: bool) -> Row<'static> {
    let mut flags = Vec::new();
    if v.withdrawn {
        flags.push("withdrawn".to_string());
    }
    if v.remote {
        flags.push(format!("on {}", v.host));
    }
    let mut cells = vec![v.id.clone(), v.kind.clone()];
    if payload {
        cells.push(v.payload.clone());
    }
    cells.extend([
        format!("{}/{}", v.in_use, v.quota),
        if v.queue {
            v.queued.to_string()
        } else {
            "-".into()
        },
        v.links.to_string(),
        flags.join(", "),
    ]);
    Row::new(cells)
}

/// The newest of `lines` in a bordered box titled `title`, as many as fit.
pub fn log_box<'a>(
    f: &mut Frame,
    area: Rect,
    title: &str,
    lines: impl DoubleEndedIterator<Item = &'a String>,
) {
    let shown: Vec<Line> = lines
        .rev()
        .take(usize::from(area.height.saturating_sub(2)))
        .map(|l| Line::from(l.clone()))
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    f.render_widget(
        Paragraph::new(shown).block(
            Block::default()
                .borders(Borders::ALL)
                .title(title.to_string()),
        ),
        area,
    );
}
