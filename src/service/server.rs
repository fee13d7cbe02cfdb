//! `photostereo serve`: the listener, tracing, signals (SIGTERM and Ctrl-C stop, SIGHUP
//! re-reads the keys) and the graceful shutdown.

use std::future::Future;

use anyhow::Context;
use tokio::net::TcpListener;

use super::config::{Config, LogFormat, ServeArgs};
use super::connections;
use super::http::router;
use super::state::AppState;

/// Serve `state` on `listener` until `shutdown` completes, then stop gracefully: no new
/// connections, idle ones closed, in-flight requests finish, running jobs get the
/// shutdown grace.
///
/// Connections get the shutdown grace too: one still open then (a request that never
/// finishes, say) is abandoned rather than waited for.
pub async fn serve_with(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let config = state.config();
    let limits = connections::Limits::resolve(config);
    let stopping = state.clone();
    connections::serve(
        listener,
        router(state.clone()),
        limits,
        state.metrics().connections.clone(),
        shutdown,
        move || {
            tracing::info!("shutting down: finishing requests and running jobs");
            stopping.begin_shutdown();
        },
        config.shutdown_grace,
    )
    .await;
    state.shutdown().await;
    Ok(())
}

/// `photostereo serve`: run the API until SIGTERM or Ctrl-C.
pub async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    init_tracing(args.log_format);
    if args.max_job_pixels.is_some() {
        tracing::warn!(
            "--max-job-pixels (PHOTOSTEREO_MAX_JOB_PIXELS) is deprecated and has no effect: jobs read their images in bands; --max-input-bytes and --max-pixels bound a job"
        );
    }
    let open_files = connections::raise_open_files_limit();
    let config = Config::from(&args);
    let listener = TcpListener::bind(&args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let state = AppState::open(config).await?;
    let addr = listener.local_addr()?;
    reload_keys_on_hangup(state.clone());
    tracing::info!(
        %addr,
        data_dir = %state.config().data_dir.display(),
        workers = state.config().workers,
        queue_length = state.config().queue_length,
        api_keys = state.keys().count(),
        open_files_limit = open_files,
        "photostereo serving; API docs at /docs"
    );
    serve_with(listener, state, shutdown_signal()).await
}

/// SIGHUP re-reads the keys file without a restart. The handler is installed before
/// this returns, so from then on a SIGHUP never takes its default action (exit).
fn reload_keys_on_hangup(state: AppState) {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let Ok(mut hangup) = signal(SignalKind::hangup()) else {
            tracing::warn!("cannot handle SIGHUP; the keys file is read at start only");
            return;
        };
        tokio::spawn(async move {
            while hangup.recv().await.is_some() {
                match state.reload_keys() {
                    Ok(n) => tracing::info!(api_keys = n, "API keys re-read"),
                    Err(e) => {
                        tracing::error!(error = %e, "API keys not re-read; the previous keys stay")
                    }
                }
            }
        });
    }
    #[cfg(not(unix))]
    let _ = state;
}

fn init_tracing(format: LogFormat) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi);
    let _ = match format {
        LogFormat::Json => builder.json().try_init(),
        LogFormat::Text => builder.try_init(),
    };
}

async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
