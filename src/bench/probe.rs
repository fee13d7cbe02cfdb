//! The probes of `bench --hostile`: at a fixed interval, `GET /healthz` and an
//! authenticated `GET /v1/jobs/{id}`, each on a new connection (as a load balancer's health
//! check would open), each given [`PROBE_TIMEOUT`]. They run on a thread and a runtime of
//! their own, so that the load the bench generates does not delay them.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::Context;

use super::client;
use super::stats::{ms, percentile};

/// A probe not answered within this is a timeout.
pub(super) const PROBE_TIMEOUT: Duration = Duration::from_secs(2);

/// What one probe got.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Outcome {
    Ok,
    /// Not a 200, or the connection failed.
    Error,
    Timeout,
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Probe {
    pub(super) ms: f64,
    pub(super) outcome: Outcome,
}

/// Every probe of one scenario.
#[derive(Debug, Default)]
pub(super) struct Probes {
    pub(super) health: Vec<Probe>,
    pub(super) status: Vec<Probe>,
    pub(super) first_failure: Option<String>,
}

impl Probes {
    /// The `p`th percentile of `probes`' times, a failed probe counting as
    /// [`PROBE_TIMEOUT`] (it would have made a load balancer wait that long or give up).
    pub(super) fn percentile(probes: &[Probe], p: f64) -> f64 {
        let mut v: Vec<f64> = probes
            .iter()
            .map(|p| match p.outcome {
                Outcome::Ok => p.ms,
                _ => ms(PROBE_TIMEOUT),
            })
            .collect();
        v.sort_by(f64::total_cmp);
        percentile(&v, p)
    }

    /// Failed probes of both kinds: (errors, timeouts).
    pub(super) fn failures(&self) -> (usize, usize) {
        let all = self.health.iter().chain(&self.status);
        let count = |o: Outcome| all.clone().filter(|p| p.outcome == o).count();
        (count(Outcome::Error), count(Outcome::Timeout))
    }
}

/// Probes running until [`stop`](Self::stop).
pub(super) struct Prober {
    stop: tokio::sync::oneshot::Sender<()>,
    thread: std::thread::JoinHandle<Probes>,
}

impl Prober {
    /// Probe `addr` every `every`: /healthz, and `status_path` with the bearer `key`.
    pub(super) fn start(
        addr: SocketAddr,
        status_path: String,
        key: &str,
        every: Duration,
    ) -> anyhow::Result<Self> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("starting the probes' runtime")?;
        let auth = format!("Bearer {key}");
        let (stop, stopped) = tokio::sync::oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("probes".into())
            .spawn(move || rt.block_on(probe_until(addr, status_path, auth, every, stopped)))
            .context("starting the probes' thread")?;
        Ok(Self { stop, thread })
    }

    /// Stop probing; every probe sent has its answer or has timed out.
    pub(super) fn stop(self) -> Probes {
        let _ = self.stop.send(());
        self.thread.join().unwrap_or_default()
    }
}

async fn probe_until(
    addr: SocketAddr,
    status_path: String,
    auth: String,
    every: Duration,
    mut stopped: tokio::sync::oneshot::Receiver<()>,
) -> Probes {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let (mut health, mut status) = (Vec::new(), Vec::new());
    loop {
        tokio::select! {
            _ = &mut stopped => break,
            _ = tick.tick() => {
                health.push(tokio::spawn(probe(addr, "/healthz".to_string(), None)));
                let (path, auth) = (status_path.clone(), Some(auth.clone()));
                status.push(tokio::spawn(probe(addr, path, auth)));
            }
        }
    }
    let mut probes = Probes::default();
    for (handles, into) in [(health, &mut probes.health), (status, &mut probes.status)] {
        for h in handles {
            let (p, failure) = h.await.unwrap_or((
                Probe {
                    ms: f64::NAN,
                    outcome: Outcome::Error,
                },
                Some("a probe task failed".into()),
            ));
            into.push(p);
            if probes.first_failure.is_none() {
                probes.first_failure = failure;
            }
        }
    }
    probes
}

/// One request on a new connection: its time and outcome, and what failed.
async fn probe(addr: SocketAddr, path: String, auth: Option<String>) -> (Probe, Option<String>) {
    let start = Instant::now();
    let exchange = async {
        let mut c = client::connect(addr).await?;
        let headers: Vec<(&str, &str)> =
            auth.iter().map(|a| ("Authorization", a.as_str())).collect();
        // The outer timeout is the one that counts.
        c.send("GET", &path, &headers, None, 2 * PROBE_TIMEOUT)
            .await
    };
    let answer = tokio::time::timeout(PROBE_TIMEOUT, exchange).await;
    let took = ms(start.elapsed());
    let (outcome, failure) = match answer {
        Ok(Ok(r)) if r.status == 200 => (Outcome::Ok, None),
        Ok(Ok(r)) => (
            Outcome::Error,
            Some(format!("GET {path}: {}", r.describe())),
        ),
        Ok(Err(e)) => (Outcome::Error, Some(format!("GET {path}: {e:#}"))),
        Err(_) => (
            Outcome::Timeout,
            Some(format!("GET {path}: no answer within {PROBE_TIMEOUT:?}")),
        ),
    };
    (Probe { ms: took, outcome }, failure)
}
