//! `muster web`: the people at the consoles, in a browser.
//!
//! An HTTP and WebSocket server (axum on tokio: the `hyper` stack the Rust ecosystem
//! serves most HTTP with, whose WebSocket support is tokio-tungstenite, already in
//! muster's tree through the Foxglove server) that serves a single-page app held inside
//! the binary (no CDN, no build step, no network) and acts on the broker for each
//! signed-in user, with exactly that user's access-file patterns ([`hub`]).
//!
//! Sign-in is with the access file's `web NAME HASH` lines (`muster keygen --web`):
//! a 160-bit token, kept hashed, traded for an HttpOnly, SameSite=Strict session cookie.
//! State changes go over the WebSocket, whose upgrade checks the Origin; the HTTP
//! ones (sign-in, sign-out) check the Origin and take JSON only, and sign-out also a
//! CSRF token. Failed sign-ins are limited per address and per name. Every page has a
//! Content-Security-Policy that allows no inline script.

pub mod auth;
pub mod hub;
pub mod pool;
mod server;
pub mod world;

pub use server::{serve, WebOptions};
