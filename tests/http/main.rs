//! The service over HTTP, in this process: a real server on 127.0.0.1:0 (`common::TestServer`)
//! and a real client. The API end to end, calibrations, the event stream, tenants and
//! webhooks, one module each.

#[path = "../binserver/mod.rs"]
mod binserver;
#[path = "../common/mod.rs"]
mod common;
#[path = "../seed/mod.rs"]
mod seed;

mod api;
mod calibrations;
mod events;
mod tenants;
mod webhooks;
