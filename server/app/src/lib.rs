//! The vsgraphs mapping server: receives robots' RGB-D frames over zenoh, runs each through the
//! frame pipeline ([`vsgraphs_pipeline`]) on the robot's worker thread, tracks robot presence,
//! and serves it all through a REST API and a web page.
//!
//! Threads: zenoh's own for the network, tokio for HTTP, and one named worker thread per robot
//! for CPU work. See ARCHITECTURE.md.

pub mod api;
pub mod certificates;
pub mod config;
pub mod detect;
pub mod history;
pub mod ingest;
pub mod queue;
pub mod robots;
pub mod simulate;
pub mod web;
pub mod zenoh_access;

use anyhow::Context;
use config::{Config, DropPolicy};
use ingest::Ingest;
use robots::Registry;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::task::JoinHandle;
use vsgraphs_pipeline::MapService;

/// A running server. Dropping it without [`Server::stop`] leaves its tasks to the runtime.
pub struct Server {
    pub registry: Arc<Registry>,
    /// Every map of the server, each with its writer.
    pub maps: MapService,
    http_addr: SocketAddr,
    ingest: Ingest,
    session: zenoh::Session,
    /// Robots see the server by it ([`vsgraphs_proto::keys::SERVER_ALIVE`]).
    alive: zenoh::liveliness::LivelinessToken,
    http: JoinHandle<std::io::Result<()>>,
    /// Set when the server stops: HTTP shuts down and pages' event streams end.
    stop_http: tokio::sync::watch::Sender<bool>,
}

/// What a configuration makes before the server touches the network: its maps (the store
/// read), the robots' table and zenoh's settings.
pub struct Prepared {
    pub maps: MapService,
    pub registry: Arc<Registry>,
    pub zenoh_config: zenoh::Config,
}

impl Server {
    /// Checks `config` and builds everything it sets up short of the network: a configuration
    /// that fails does so here, with the setting that is wrong.
    pub async fn prepare(config: &Config) -> anyhow::Result<Prepared> {
        config.validate()?;
        // Fail now, not in the first robot's worker, if the marker dictionary cannot load.
        let dictionary = config
            .semantics
            .dictionary()
            .context("reading the semantic dictionary")?;
        for warning in dictionary.iter().flat_map(|d| &d.warnings) {
            tracing::warn!(warning, "semantic dictionary");
        }
        let maps = MapService::with_semantics(config.semantics.enabled, dictionary)
            .with_whole_map_optimisation(config.semantics.optimise_every_keyframes)
            .with_live_merges(config.atlas.merge_maps)
            // A live robot's worker must not wait for a merge (hundreds of ms on big maps).
            .with_background_merges(true)
            .with_loop_closing(config.atlas.close_loops)
            .with_mapping(config.tracking.tracker().mapping());
        let maps = if config.store.path.as_os_str().is_empty() {
            maps
        } else {
            // Reading a store of large maps takes seconds: off the async runtime.
            let every = std::time::Duration::from_secs_f64(config.store.save_every_s);
            let path = config.store.path.clone();
            tokio::task::spawn_blocking(move || maps.with_store(&path, every))
                .await
                .context("opening the map store")?
                .context("opening the map store")?
        };
        vsgraphs_pipeline::FrameProcessor::new(
            &config.markers,
            &config.tracking,
            config.ingest.max_frame_bytes,
            maps.clone(),
        )
        .context("setting up marker detection")?;
        let registry = Arc::new(
            Registry::new(
                config.ingest.max_robots,
                config.ingest.queue_capacity,
                config.ingest.drop_policy == DropPolicy::DropOldest,
            )
            .with_trajectory_poses(config.ingest.trajectory_poses)
            .with_max_rate_hz(config.ingest.max_rate_hz),
        );
        let mut zenoh_config = config.zenoh.to_config()?;
        // zenoh gathers a message's fragments until it is whole, by default up to a gigabyte
        // per link. Twice the frame limit: a frame a little too large still arrives and is
        // refused with its reason; beyond that zenoh drops it.
        let max_message = config.ingest.max_frame_bytes.saturating_mul(2);
        zenoh_config
            .insert_json5(
                "transport/link/rx/max_message_size",
                &max_message.to_string(),
            )
            .map_err(|e| anyhow::anyhow!("zenoh message size: {e}"))?;
        if !config.ingest.allowed_robots.is_empty() {
            let rules = zenoh_access::rules(&config.ingest.allowed_robots, &config.ros.robots)?;
            zenoh_config
                .insert_json5("access_control", &rules.to_string())
                .map_err(|e| anyhow::anyhow!("zenoh access control: {e}"))?;
        }
        Ok(Prepared {
            maps,
            registry,
            zenoh_config,
        })
    }

    /// Checks the configuration, opens zenoh, starts ingest and the HTTP server.
    pub async fn start(config: Config) -> anyhow::Result<Self> {
        let Prepared {
            maps,
            registry,
            zenoh_config,
        } = Self::prepare(&config).await?;
        let open_network = config.zenoh.listen.iter().any(|e| {
            !(e.contains("/127.0.0.1:") || e.contains("/[::1]:") || e.contains("/localhost:"))
        });
        if open_network && !config.zenoh.tls.mutual {
            tracing::warn!(
                listen = ?config.zenoh.listen,
                "zenoh listens beyond this machine without mutual TLS: anyone on the network \
                 can publish frames as any robot ([zenoh.tls], [ingest] allowed_robots)"
            );
        }
        let session = zenoh::open(zenoh_config)
            .await
            .map_err(|e| anyhow::anyhow!("opening zenoh on {:?}: {e}", config.zenoh.listen))?;
        let listener = tokio::net::TcpListener::bind(config.http.listen)
            .await
            .with_context(|| format!("binding HTTP to {}", config.http.listen))?;
        let http_addr = listener.local_addr()?;
        let config = Arc::new(config);
        let ingest = Ingest::start(&session, registry.clone(), config.clone(), maps.clone())
            .await
            .map_err(|e| anyhow::anyhow!("subscribing on zenoh: {e}"))?;
        let alive = session
            .liveliness()
            .declare_token(vsgraphs_proto::keys::SERVER_ALIVE)
            .await
            .map_err(|e| anyhow::anyhow!("declaring the server's liveliness: {e}"))?;
        let access = api::access::Access::new(&config.http.admin_token, &config.http.read_token);
        if access.admin_token.is_none() && !http_addr.ip().is_loopback() {
            tracing::warn!(
                %http_addr,
                "the API listens beyond this machine without an admin token: anyone who reaches \
                 it can replace the dictionary and add maps ([http] admin_token)"
            );
        }
        let (stop_http, mut stopped) = tokio::sync::watch::channel(false);
        let app = api::router(
            registry.clone(),
            maps.clone(),
            config.http.max_map_file_bytes,
            access,
            stopped.clone(),
        )
        .merge(web::router());
        let http = tokio::spawn(async move {
            axum::serve(listener, app)
                .with_graceful_shutdown(async move {
                    let _ = stopped.wait_for(|stop| *stop).await;
                })
                .await
        });
        tracing::info!(%http_addr, zenoh = ?config.zenoh.listen, "server started");
        Ok(Self {
            registry,
            maps,
            http_addr,
            ingest,
            session,
            alive,
            http,
            stop_http,
        })
    }

    /// Where the REST API and the page are served.
    pub fn http_addr(&self) -> SocketAddr {
        self.http_addr
    }

    /// Says goodbye to the robots (withdraws the server's liveliness), closes zenoh, drains the
    /// robots' queues, stops the maps' writers (each hands its last changes to the store, which
    /// commits them), and stops HTTP.
    pub async fn stop(self) -> anyhow::Result<()> {
        let Server {
            ingest,
            maps,
            session,
            alive,
            http,
            stop_http,
            ..
        } = self;
        alive
            .undeclare()
            .await
            .map_err(|e| anyhow::anyhow!("withdrawing the server's liveliness: {e}"))?;
        session
            .close()
            .await
            .map_err(|e| anyhow::anyhow!("closing zenoh: {e}"))?;
        tokio::task::spawn_blocking(move || {
            ingest.stop();
            maps.stop();
        })
        .await?;
        let _ = stop_http.send(true);
        http.await??;
        Ok(())
    }
}
