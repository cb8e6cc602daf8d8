//! The pipeline's configuration file (TOML): which scene, which transport, how many workers of
//! each stage, the backpressure policy, time limits and the registration settings. Unknown keys
//! are refused; `validate` runs once and names the field at fault.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::core::change::fusion::FusionConfig;
use crate::core::change::stereo::{
    NeighbourConfig, StereoConfig, DEFAULT_DISPARITY_SIGMA_PX, MAX_NEIGHBOURS,
};
use crate::core::change::ChangeConfig;
use crate::core::frame::{NeighbourOrder, RegistrationConfig};
use crate::stage::ingest::SourceConfig;
use crate::transport::zenoh::ZenohSettings;
use crate::transport::{Backend, TransportConfig};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineConfig {
    /// A synthetic scene folder (as `asgreg synth` writes it): `run` and `launch` make it when it
    /// is missing and take the mesh and the 30 px initial poses from it. For demonstrations and
    /// tests; a real deployment sets `mesh` and `[source]` instead.
    pub synthetic_scene: Option<PathBuf>,
    /// Mesh file (PLY or OBJ) every stage that needs geometry loads.
    pub mesh: PathBuf,
    /// Refuse a mesh that would take more memory than this to load (MiB), judged from its header
    /// before loading it, as `register --max-mesh-mib` (which `run`, `launch` and `stage` take too,
    /// over this). `run` and `launch` check it before any stage starts. Unset: no limit.
    pub max_mesh_mib: Option<u64>,
    pub source: SourceConfig,
    /// Which transport moves the messages: crossbeam (one process), iceoryx2 (processes on one
    /// host) or zenoh (hosts).
    pub backend: Backend,
    pub transport: TransportConfig,
    pub zenoh: ZenohSettings,
    pub workers: Workers,
    pub backpressure: Backpressure,
    pub timeouts: Timeouts,
    pub launch: LaunchSettings,
    pub registration: RegistrationConfig,
    /// Change detection of the change stage (`workers.change` > 0), as `asgreg changes`.
    pub change: ChangeConfig,
    /// How the fusion stage merges the frames' change regions into objects, and how much of
    /// the frames' sights it holds in memory.
    pub fusion: FusionSettings,
    /// Depth of frames without a given depth map: stereo from registered neighbours.
    pub stereo: StereoSettings,
    /// Folder of the run's durable state: the results journal (`<pipeline>.results-journal`,
    /// the frames whose result is published), which a restarted ingest resumes from and a
    /// restarted verify reads so it publishes no result twice. Ingest and verify must see the
    /// same folder (same host). Unset: `asgreg-state` in the system's temporary folder. `asgreg
    /// run` keeps a folder of its own in it (unset: in the temporary folder), removed at the end.
    /// `run` and `launch` check that it can be written before any stage starts; a journal that
    /// cannot be written later (a full disk) fails each frame's result with the reason.
    pub state_dir: Option<PathBuf>,
    /// `asgreg bench pipeline --simulate`: every stage sleeps these per-job times instead of
    /// computing (the loops, dispatchers and transports are the real ones). Unset: real work.
    pub simulate: Option<crate::stage::simulate::SimulatedWork>,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            synthetic_scene: None,
            mesh: PathBuf::new(),
            max_mesh_mib: None,
            source: SourceConfig::default(),
            backend: Backend::Crossbeam,
            transport: TransportConfig::default(),
            zenoh: ZenohSettings::default(),
            workers: Workers::default(),
            backpressure: Backpressure::default(),
            timeouts: Timeouts::default(),
            launch: LaunchSettings::default(),
            registration: RegistrationConfig::default(),
            change: ChangeConfig::default(),
            fusion: FusionSettings::default(),
            stereo: StereoSettings::default(),
            state_dir: None,
            simulate: None,
        }
    }
}

/// The fusion stage (`[fusion]`): how it merges the frames' change regions into objects (a
/// `FusionConfig`, as `asgreg changes`), and the memory its frames' sights may take.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FusionSettings {
    /// Footprints closer than this are one object, metres.
    pub merge_distance_m: f64,
    /// Distinct frames needed to confirm an object.
    pub min_frames: usize,
    /// Most MB (10^6 bytes) of the frames' sights (photo depth, model depth, pose term; about
    /// 1.7 MB per frame at 505 × 275) fusion holds in memory; the others are read back from the
    /// state folder (`<pipeline>.sights`) when the free-space test needs a frame that can see an
    /// object. Every frame's footprint (a few hundred bytes) stays. 0: a sight is held only
    /// while it is read. The change set does not depend on it.
    pub max_sights_in_memory_mb: u64,
}

impl Default for FusionSettings {
    fn default() -> Self {
        let merge = FusionConfig::default();
        Self {
            merge_distance_m: merge.merge_distance_m,
            min_frames: merge.min_frames,
            max_sights_in_memory_mb: 256,
        }
    }
}

impl FusionSettings {
    /// How regions are merged into objects.
    pub fn merge(&self) -> FusionConfig {
        FusionConfig {
            merge_distance_m: self.merge_distance_m,
            min_frames: self.min_frames,
        }
    }
}

/// The change stage's depth for a frame without a given depth map (`[stereo]`): plane-sweep
/// stereo against registered neighbours, chosen by verify among the accepted frames of the
/// stream within `window_frames` of it (before and after, in frame order). The defaults are
/// `asgreg changes`'s, so on a stream no longer than the window both choose from the same frames.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StereoSettings {
    /// Which registered frames are a frame's neighbours (`count`: 1–4).
    pub neighbours: NeighbourConfig,
    /// The plane sweep.
    pub sweep: StereoConfig,
    /// Disparity error of the stereo depth, working pixels (the change threshold's stereo term).
    pub disparity_sigma_px: f64,
    /// Frames before and after a frame whose accepted ones are its candidate neighbours; its
    /// change job waits until the `window_frames` frames after it are decided (or the stream
    /// ends), so this is also the change result's delay in frames.
    pub window_frames: u64,
}

impl Default for StereoSettings {
    fn default() -> Self {
        Self {
            neighbours: NeighbourConfig::default(),
            sweep: StereoConfig::default(),
            disparity_sigma_px: DEFAULT_DISPARITY_SIGMA_PX,
            window_frames: 6,
        }
    }
}

/// Worker counts per stage (ingest and verify are always one).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Workers {
    /// Render workers; each owns the flow link of its share of the flow workers (flow worker
    /// `w` serves render worker `w % render`), at most `flow`.
    pub render: u32,
    /// The expensive stage: the (frame, coarse pose) jobs are shared among these.
    pub flow: u32,
    /// Flow workers the launcher starts itself; the rest attach from other hosts (zenoh).
    pub flow_local: Option<u32>,
    /// Pose workers; each takes the coarse poses whose (frame, coarse index) falls to it
    /// (`runtime::nodes::pose_worker_of`), so every coarse pose is solved by exactly one.
    pub pose: u32,
    /// Threads of the verify stage that decide complete frames (plausibility check, final
    /// refinement), beside verify's loop, which keeps reading its inbox meanwhile. Results stay
    /// one per frame.
    pub verify_threads: u32,
    /// Change detection workers (accepted frames' change maps, dispatched like flow), plus one
    /// fusion stage when > 0 (the default: 1). 0: no change detection.
    pub change: u32,
    /// Jobs a worker holds at once (1: strict sharing; 2 hides transport latency).
    pub slots: u32,
}

impl Default for Workers {
    fn default() -> Self {
        Self {
            render: 1,
            flow: 2,
            flow_local: None,
            pose: 1,
            verify_threads: 1,
            change: 1,
            slots: 1,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BackpressurePolicy {
    /// The source waits for the pipeline (no frame lost; a live camera falls behind).
    #[default]
    Block,
    /// The oldest waiting frame is dropped; it still gets a result, failed with reason
    /// "dropped", and the drop is counted.
    DropOldest,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Backpressure {
    pub policy: BackpressurePolicy,
    /// Frames waiting between ingest and render before the policy applies.
    pub frames_queued: usize,
    /// Flow jobs waiting between render and the flow workers before render stops taking frames
    /// (at least one frame's coarse poses).
    pub flow_jobs_queued: usize,
}

impl Default for Backpressure {
    fn default() -> Self {
        Self {
            policy: BackpressurePolicy::Block,
            frames_queued: 2,
            flow_jobs_queued: 30,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Timeouts {
    /// A frame whose hypotheses are not all in after this long gets a failed result, s.
    pub frame_timeout_s: f64,
    /// A worker silent this long with jobs outstanding has them redone elsewhere, s (longer than
    /// the slowest job).
    pub worker_silence_s: f64,
    /// How long a stage waits for the stage it sends to before giving up at start, s.
    pub startup_s: f64,
    /// A published result (pose or change) that the collector has not acknowledged after this
    /// long is sent again, then after twice as long, ... up to 16 s (`runtime::ack`), s. 0: never
    /// sent again (a result lost in flight stays lost).
    pub resend_after_s: f64,
    /// A frame that render has handed on and that has no pose result this long after is sent
    /// down the pipeline again — when a later frame already has its result, or when no result at
    /// all came in for that long — then after twice as long, up to 8× (`runtime::nodes`,
    /// `Recovery::redo_unanswered`): every message of it was lost in flight (over zenoh while the
    /// router restarted), so verify never heard of it and its own timeout cannot fail it. A
    /// repeat verify already has is ignored, s. 0: never.
    pub redo_unanswered_after_s: f64,
}

impl Default for Timeouts {
    fn default() -> Self {
        Self {
            frame_timeout_s: 300.0,
            worker_silence_s: 60.0,
            startup_s: 60.0,
            resend_after_s: 2.0,
            redo_unanswered_after_s: 20.0,
        }
    }
}

/// What `asgreg launch` does beyond starting the stages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LaunchSettings {
    /// With the zenoh backend: endpoints the launcher's own zenoh router listens on (stages and
    /// remote workers connect to it). Empty: no router (one runs elsewhere).
    pub zenoh_router_listen: Vec<String>,
    /// With the zenoh backend: a zenoh json5 router config the launcher's router starts from
    /// (TLS, access control: `deploy/zenoh/router-tls.json5`, `router-tls-acl.json5`); its
    /// listen endpoints are replaced by `zenoh_router_listen`. Relative to the config file.
    pub zenoh_router_config: Option<PathBuf>,
    /// Restart intensity, as Erlang's and systemd's supervisors have it: a stage worker that
    /// dies more than `max_restarts` times within `restart_window_s` makes the launcher give up
    /// on the run (it crashes faster than it can work); slower crashes are restarted forever.
    /// 0: never restart.
    pub max_restarts: u32,
    /// The sliding window of `max_restarts`, s.
    pub restart_window_s: f64,
    /// How long a stage has to stop after SIGTERM (finish or hand back its job, flush, close
    /// its shared memory) before the launcher sends SIGKILL, s.
    pub stop_grace_s: f64,
    /// Longest run, s; frames without a result by then are reported missing.
    pub deadline_s: f64,
}

impl Default for LaunchSettings {
    fn default() -> Self {
        Self {
            zenoh_router_listen: Vec::new(),
            zenoh_router_config: None,
            max_restarts: 5,
            restart_window_s: 60.0,
            stop_grace_s: 10.0,
            deadline_s: 3600.0,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: cannot read: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {detail}")]
    Parse { path: PathBuf, detail: String },
    #[error("{path}: field '{field}': {detail}")]
    Invalid {
        path: PathBuf,
        field: &'static str,
        detail: String,
    },
}

impl PipelineConfig {
    /// Reads and validates a TOML file; relative paths in it are relative to the file.
    pub fn read(path: &Path) -> Result<Self, ConfigError> {
        let text = crate::io::text::read_utf8(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut config: PipelineConfig =
            toml::from_str(&text).map_err(|error| ConfigError::Parse {
                path: path.to_path_buf(),
                detail: error.to_string(),
            })?;
        let base = path.parent().unwrap_or(Path::new("."));
        config.resolve_paths(base);
        config.validate(path)?;
        Ok(config)
    }

    /// Whether the change and fusion stages run (`workers.change` > 0).
    pub fn changes_enabled(&self) -> bool {
        self.workers.change > 0
    }

    fn resolve_paths(&mut self, base: &Path) {
        let resolve = |p: &mut PathBuf| {
            if !p.as_os_str().is_empty() && p.is_relative() {
                *p = base.join(&*p);
            }
        };
        if let Some(scene) = &mut self.synthetic_scene {
            resolve(scene);
        }
        if let Some(scene) = &self.synthetic_scene {
            if self.mesh.as_os_str().is_empty() {
                self.mesh = scene.join("model.ply");
            }
            if self.source.poses.as_os_str().is_empty() {
                let defaults = SourceConfig::scene(scene, 30);
                self.source.images = defaults.images;
                self.source.cameras = defaults.cameras;
                self.source.poses = defaults.poses;
                self.source.intrinsics_known = true;
            }
        }
        resolve(&mut self.mesh);
        resolve(&mut self.source.images);
        resolve(&mut self.source.cameras);
        resolve(&mut self.source.poses);
        if let Some(depth) = &mut self.source.depth {
            resolve(depth);
        }
        if let Some(state_dir) = &mut self.state_dir {
            resolve(state_dir);
        }
        if let Some(file) = &mut self.zenoh.config_file {
            resolve(file);
        }
        if let Some(file) = &mut self.launch.zenoh_router_config {
            resolve(file);
        }
    }

    pub fn validate(&self, path: &Path) -> Result<(), ConfigError> {
        let invalid = |field: &'static str, detail: String| ConfigError::Invalid {
            path: path.to_path_buf(),
            field,
            detail,
        };
        if self.mesh.as_os_str().is_empty() {
            return Err(invalid(
                "mesh",
                "set the mesh file (PLY or OBJ)".to_string(),
            ));
        }
        if self.workers.render == 0 || self.workers.flow == 0 || self.workers.pose == 0 {
            return Err(invalid(
                "workers",
                "render, flow and pose need at least one worker each".to_string(),
            ));
        }
        if self.workers.render > self.workers.flow {
            return Err(invalid(
                "workers.render",
                "each render worker feeds its own flow workers (flow worker w serves render worker w % render): at most workers.flow".to_string(),
            ));
        }
        if self.registration.neighbour_pose.enabled
            && self.registration.neighbour_pose.order != NeighbourOrder::Feed
        {
            return Err(invalid(
                "registration.neighbour_pose.order",
                "a pipeline is a feed: a frame borrows only from the frames before it; set \"feed\" (\"set\" is for `register` over photos without an order)".to_string(),
            ));
        }
        if self.workers.verify_threads == 0 {
            return Err(invalid(
                "workers.verify_threads",
                "verify needs at least one thread".to_string(),
            ));
        }
        if self
            .workers
            .flow_local
            .is_some_and(|n| n > self.workers.flow)
        {
            return Err(invalid(
                "workers.flow_local",
                "cannot exceed workers.flow".to_string(),
            ));
        }
        if self.launch.zenoh_router_config.is_some() && self.launch.zenoh_router_listen.is_empty() {
            return Err(invalid(
                "launch.zenoh_router_config",
                "needs launch.zenoh_router_listen: the endpoints the launcher's router listens on \
                 (e.g. [\"tcp/127.0.0.1:7447\", \"tls/192.168.10.1:7448\"])"
                    .to_string(),
            ));
        }
        let coarse = self.registration.coarse_pose_count;
        if self.backpressure.flow_jobs_queued < coarse {
            return Err(invalid(
                "backpressure.flow_jobs_queued",
                format!("must hold at least one frame's coarse poses ({coarse})"),
            ));
        }
        if self.backpressure.frames_queued == 0 {
            return Err(invalid(
                "backpressure.frames_queued",
                "must be at least 1".to_string(),
            ));
        }
        for (field, value) in [
            ("timeouts.frame_timeout_s", self.timeouts.frame_timeout_s),
            ("timeouts.worker_silence_s", self.timeouts.worker_silence_s),
            ("timeouts.startup_s", self.timeouts.startup_s),
            ("launch.restart_window_s", self.launch.restart_window_s),
            ("launch.stop_grace_s", self.launch.stop_grace_s),
            ("launch.deadline_s", self.launch.deadline_s),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(invalid(
                    field,
                    format!("must be a positive number of seconds, got {value}"),
                ));
            }
        }
        let resend = self.timeouts.resend_after_s;
        if !(resend.is_finite() && resend >= 0.0) {
            return Err(invalid(
                "timeouts.resend_after_s",
                format!("must be ≥ 0 s (0: never send a result again), got {resend}"),
            ));
        }
        let redo = self.timeouts.redo_unanswered_after_s;
        if !(redo.is_finite() && redo >= 0.0) {
            return Err(invalid(
                "timeouts.redo_unanswered_after_s",
                format!("must be ≥ 0 s (0: never send an unanswered frame again), got {redo}"),
            ));
        }
        if !(self.source.rate_hz.is_finite() && self.source.rate_hz >= 0.0) {
            return Err(invalid(
                "source.rate_hz",
                format!(
                    "must be ≥ 0 (0: as fast as possible), got {}",
                    self.source.rate_hz
                ),
            ));
        }
        self.registration
            .validate()
            .map_err(|e| invalid("registration", e.to_string()))?;
        self.change
            .validate()
            .map_err(|e| invalid("change", e.to_string()))?;
        self.stereo
            .sweep
            .validate()
            .map_err(|e| invalid("stereo.sweep", e.to_string()))?;
        self.stereo
            .neighbours
            .validate()
            .map_err(|e| invalid("stereo.neighbours", e.to_string()))?;
        let count = self.stereo.neighbours.count;
        let sigma_ok =
            self.stereo.disparity_sigma_px.is_finite() && self.stereo.disparity_sigma_px > 0.0;
        if !((1..=MAX_NEIGHBOURS).contains(&count) && sigma_ok) {
            return Err(invalid(
                "stereo",
                format!(
                    "neighbours.count must be 1..={MAX_NEIGHBOURS} (got {count}) and disparity_sigma_px > 0 (got {})",
                    self.stereo.disparity_sigma_px
                ),
            ));
        }
        if !(self.fusion.merge_distance_m.is_finite()
            && self.fusion.merge_distance_m >= 0.0
            && self.fusion.min_frames >= 1)
        {
            return Err(invalid(
                "fusion",
                format!(
                    "merge_distance_m must be ≥ 0 (got {}) and min_frames ≥ 1 (got {})",
                    self.fusion.merge_distance_m, self.fusion.min_frames
                ),
            ));
        }
        Ok(())
    }
}
