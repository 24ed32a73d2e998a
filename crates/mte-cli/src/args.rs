//! Command-line arguments (clap derive).
//!
//! House style: every flag has a doc comment (it becomes the help text) that states the
//! unit and the default; long names are kebab-case; values that name a choice are enums or
//! parse through the library's own `FromStr` (aggregators), never free strings.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};
use mte_ensemble::Aggregator;
use mte_sim::expert::ExpertConfig;

/// mte: robust temporal ensembling for action-chunked robot policies.
#[derive(Debug, Parser)]
#[command(name = "mte", version, about, long_about = None)]
pub struct Cli {
    /// Print less (errors and requested output only).
    #[arg(short, long, global = true, conflicts_with = "verbose")]
    pub quiet: bool,
    /// Print more detail (repeat for more).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    /// Hide progress bars (they are also hidden when stderr is not a terminal).
    #[arg(long, global = true)]
    pub no_progress: bool,
    /// Output format of results on stdout.
    #[arg(long, global = true, value_enum, default_value_t = Format::Text)]
    pub format: Format,
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Format {
    /// Tables for people.
    Text,
    /// One JSON document for programs.
    Json,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// The PushT experiment with the bundled policy: blank-frame bursts, exp-weighted mean
    /// vs median, paired episodes, a report (a few minutes on 2 cores).
    Demo(DemoArgs),
    /// Film one episode twice from the same seed under the same corruption, with two
    /// aggregators side by side (the paper's Figure 2): an animated GIF and a strip.
    Film(FilmArgs),
    /// Run a sweep spec (TOML grid of policy x corruption x q x h) into a run directory.
    Sweep(SweepArgs),
    /// Tables, paired tests and plots from one or more run directories.
    Report(ReportArgs),
    /// Synthetic stress test: what corrupted queries do to each aggregator (no simulator).
    Synthetic(SyntheticArgs),
    /// Adversarial attacks.
    #[command(subcommand)]
    Attack(AttackCommand),
    /// Defences: encoder adversarial fine-tuning and its gradient probe.
    #[command(subcommand)]
    Defend(DefendCommand),
    /// Runtime monitors (TIDE, ACC) on recorded runs: thresholds from clean episodes, then
    /// firing rates and AUROC per cell.
    #[command(subcommand)]
    Monitor(MonitorCommand),
    /// Work with recorded chunk streams.
    #[command(subcommand)]
    Ensemble(EnsembleCommand),
    /// The native PushT simulator: render frames, roll out policies, measure speed.
    #[command(subcommand)]
    Sim(SimCommand),
    /// Demonstration datasets.
    #[command(subcommand)]
    Data(DataCommand),
    /// Train policies.
    #[command(subcommand)]
    Train(TrainCommand),
    /// Evaluate policies on PushT.
    #[command(subcommand)]
    Eval(EvalCommand),
    /// Environments behind the bridge (gymnasium, robomimic): scripted experts, speed.
    #[command(subcommand)]
    Env(EnvCommand),
}

/// `mte env ...`
#[derive(Debug, Subcommand)]
pub enum EnvCommand {
    /// Run a bridge target's scripted expert on seeded episodes and report its success.
    Expert(EnvExpertArgs),
    /// Control steps per second through the bridge (the expert's actions, or zeros).
    Bench(EnvBenchArgs),
}

/// `mte env expert`
#[derive(Debug, Args)]
pub struct EnvExpertArgs {
    /// The target: `robomimic:lift|can|square` (the worker's Python: `MTE_PYTHON`, else the
    /// environment `tools/env-setup robomimic` made).
    #[arg(long)]
    pub env: mte_eval::bridge::Target,
    /// First reset seed (Diffusion Policy's test seeds start at 100000).
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Episodes (seeds seed..seed+episodes).
    #[arg(long, default_value_t = 50, value_parser = at_least_one)]
    pub episodes: usize,
    /// Step limit per episode (robomimic's ph horizon: 400).
    #[arg(long, default_value_t = 400, value_parser = at_least_one)]
    pub max_steps: usize,
}

/// `mte env bench`
#[derive(Debug, Args)]
pub struct EnvBenchArgs {
    /// The target (as for `mte env expert`; `gym:` targets step with zero actions).
    #[arg(long)]
    pub env: mte_eval::bridge::Target,
    /// Control steps to time (after one reset).
    #[arg(long, default_value_t = 400, value_parser = at_least_one)]
    pub steps: usize,
    /// Also observe a camera frame of this size every step (`84x84`); state only otherwise.
    #[arg(long, value_parser = size)]
    pub image: Option<(usize, usize)>,
    /// Reset seed.
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
}

/// `mte eval ...`
#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Roll out a trained policy checkpoint on seeded PushT episodes (clean observations).
    Policy(EvalPolicyArgs),
}

/// `mte eval policy`
#[derive(Debug, Args)]
pub struct EvalPolicyArgs {
    /// Checkpoint directory (config.json + model.safetensors), or `expert:pusht`: the
    /// scripted expert re-planning at every query, as a noise-free chunked policy.
    #[arg(long, value_name = "DIR")]
    pub checkpoint: PathBuf,
    /// First reset seed (Diffusion Policy's test seeds start at 100000).
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Episodes (seeds seed..seed+episodes).
    #[arg(long, default_value_t = 50, value_parser = at_least_one)]
    pub episodes: usize,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// Where the episodes run: `pusht` (native), or through the environment bridge
    /// `gym:<module>/<EnvId>[?key=value&...]` or `robomimic:lift|can|square` (the worker's
    /// Python: `MTE_PYTHON`, else the environment `tools/env-setup` made).
    #[arg(long, default_value = "pusht")]
    pub env: mte_eval::environment::EnvTarget,
    /// Control steps between queries.
    #[arg(long, default_value_t = 8, value_parser = at_least_one)]
    pub stride: usize,
    /// `open-loop`, or an aggregator text form (e.g. `ewm:0.01`, `median`).
    #[arg(long, default_value = "ewm:0.01", value_parser = arm)]
    pub execution: String,
    /// Step limit per episode.
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
    /// Seed of the policy's sampling noise.
    #[arg(long, default_value_t = 0)]
    pub noise_seed: u64,
    /// `independent`: fresh sampling noise per query (as deployed); `fixed`: the same noise
    /// at every query of an episode (a chunk is then a deterministic function of its
    /// observations), an analysis control for the clean-data confound.
    #[arg(long, value_enum, default_value_t = SamplingArg::Independent)]
    pub sampling: SamplingArg,
    /// Use only the first N executable rows of each chunk (from row T_o - 1), as for a
    /// policy predicting fewer rows: fewer candidates per step. Default: all of them.
    #[arg(long)]
    pub span: Option<usize>,
    /// A corruption, as JSON in the run manifest's form, e.g. `{"fault": {"kind": "blank"},
    /// "schedule": {"kind": "burst", "q": 2, "phase": 3}}`; default: clean. The candidate
    /// statistics then also measure each corrupted candidate against the clean ones.
    #[arg(long, value_name = "JSON")]
    pub corruption: Option<String>,
    /// Where the policy runs: `cpu`, or `cuda` / `cuda:N` in a build with the `cuda` feature.
    #[arg(long, default_value = "cpu")]
    pub device: mte_policy::ComputeDevice,
}

/// How sampling noise varies across queries (`mte_eval::pusht::Sampling`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SamplingArg {
    /// Fresh noise per query.
    Independent,
    /// The same noise at every query of an episode.
    Fixed,
}

impl From<SamplingArg> for mte_eval::pusht::Sampling {
    fn from(s: SamplingArg) -> Self {
        match s {
            SamplingArg::Independent => Self::Independent,
            SamplingArg::Fixed => Self::Fixed,
        }
    }
}

/// `mte train ...`
#[derive(Debug, Subcommand)]
pub enum TrainCommand {
    /// Train Diffusion Policy on an `mte data generate` dataset.
    Diffusion(TrainDiffusionArgs),
    /// Train ACT (PushT keypoints, or the camera with `--obs image`) on an `mte data generate`
    /// dataset.
    Act(TrainActArgs),
    /// Pre-train an image policy's encoder to regress the block keypoints (a warm start for
    /// `train diffusion --init`; the dataset needs `--obs keypoints,pixels`).
    Encoder(TrainEncoderArgs),
}

/// `mte train act`
#[derive(Debug, Args)]
pub struct TrainActArgs {
    /// Dataset directory (from `mte data generate`).
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Model preset: `paper` is LeRobot's ACT (width 512, 4 + 1 layers, chunk 100), `cpu` the
    /// same at width 128 with 2 encoder layers.
    #[arg(long, value_enum, default_value_t = PresetArg::Cpu)]
    pub preset: PresetArg,
    /// JSON file of config fields overriding the preset (LeRobot's config.json names, e.g.
    /// `{"chunk_size": 20, "n_action_steps": 20}`); an unknown field is an error.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Observation to condition on: `keypoints` (agent position + 16 block keypoints) or
    /// `image` (agent position + the 96 x 96 frame through ResNet-18 with frozen BatchNorm;
    /// the dataset needs `--obs state,keypoints,pixels`).
    #[arg(long, value_enum, default_value_t = PolicyObsArg::Keypoints)]
    pub obs: PolicyObsArg,
    /// With `--obs image`: also the wrist camera (`observation.images.wrist`, from `mte
    /// data generate --obs pixels,wrist`), its feature-map tokens after the scene camera's
    /// through the one backbone (LeRobot's ACT).
    #[arg(long)]
    pub wrist: bool,
    /// Optimiser steps in total (a resumed run continues to this count).
    #[arg(long, default_value_t = 20000)]
    pub steps: usize,
    /// Frames per batch.
    #[arg(long, default_value_t = 64)]
    pub batch_size: usize,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Checkpoint every this many steps.
    #[arg(long, default_value_t = 2000)]
    pub checkpoint_every: usize,
    /// Start from the weights of an ACT checkpoint of the same configuration (its
    /// model.safetensors, e.g. a bundled policy's), to train it further; ignored on resume.
    #[arg(long, value_name = "FILE")]
    pub init: Option<PathBuf>,
    /// With `--obs image`: take the camera backbone from an image Diffusion Policy's encoder
    /// (its model.safetensors; same width, e.g. assets/policies/pusht_image_cpu_v3), its
    /// GroupNorms turned into frozen BatchNorms with statistics calibrated on training
    /// frames; the conversion's relative error is reported. Ignored on resume and with --init.
    #[arg(long, value_name = "FILE", conflicts_with = "init")]
    pub backbone_from: Option<PathBuf>,
    /// With `--obs image`: keep the backbone fixed and cache each frame's feature map once
    /// (exact: ACT trains without augmentation); a step then costs about a keypoint policy's.
    #[arg(long)]
    pub freeze_backbone: bool,
    /// Learning rate over the run: `constant` (LeRobot's ACT) or `cosine` (Diffusion
    /// Policy's: linear warm-up over `--lr-warmup` steps, then cosine decay to 0 at the last).
    #[arg(long, value_enum, default_value_t = LrScheduleArg::Constant)]
    pub lr_schedule: LrScheduleArg,
    /// With `--lr-schedule cosine`: warm-up steps.
    #[arg(long, default_value_t = 500)]
    pub lr_warmup: usize,
    /// Keep an exponential moving average of the weights with this decay ceiling (Diffusion
    /// Policy's is 0.999): the checkpoint's model.safetensors is then the average and
    /// raw_model.safetensors the optimised weights (what a resume continues from).
    #[arg(long, value_name = "DECAY")]
    pub ema: Option<f64>,
    /// Output directory; if it holds a training state, training resumes from it.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `mte train act --lr-schedule`
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LrScheduleArg {
    /// The config's learning rates throughout.
    Constant,
    /// Linear warm-up, then cosine decay to 0.
    Cosine,
}

/// `mte train encoder`
#[derive(Debug, Args)]
pub struct TrainEncoderArgs {
    /// Dataset directory (from `mte data generate --obs state,keypoints,pixels`); repeat it
    /// to pre-train on several as one (the first one's frame size and object-state width
    /// set the encoder's).
    #[arg(long, value_name = "DIR", required = true)]
    pub data: Vec<PathBuf>,
    /// Model preset (its encoder width, crop and keypoint count).
    #[arg(long, value_enum, default_value_t = PresetArg::Cpu)]
    pub preset: PresetArg,
    /// JSON file of config fields overriding the preset.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Optimiser steps.
    #[arg(long, default_value_t = 2_000)]
    pub steps: usize,
    /// Frames per batch.
    #[arg(long, default_value_t = 64)]
    pub batch_size: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Seed of the initialisation and every draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory: encoder.safetensors and pretrain.json.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// Model presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PresetArg {
    /// The model's published configuration (the command's `--preset` text says which): for
    /// GPUs.
    Paper,
    /// The same model made small enough to train on 2 CPU cores.
    Cpu,
}

/// The noise network of `mte train diffusion`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BackboneArg {
    /// The conditional U-Net 1D.
    Unet,
    /// `TransformerForDiffusion`.
    Transformer,
}

/// Observation a policy conditions on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PolicyObsArg {
    /// 16 block keypoints + agent position.
    Keypoints,
    /// 96 x 96 frame + agent position.
    Image,
}

/// `mte train diffusion`
#[derive(Debug, Args)]
pub struct TrainDiffusionArgs {
    /// Dataset directory (from `mte data generate` or `mte data takeover`); repeat it to
    /// train on several as one (episodes in order, normalisation statistics pooled; the
    /// first one's feature sizes set the policy's).
    #[arg(long, value_name = "DIR", required = true)]
    pub data: Vec<PathBuf>,
    /// Model preset: `paper` is Diffusion Policy's published PushT configuration of the
    /// backbone (the U-Net's down_dims 512/1024/2048, 100 DDPM steps), `cpu` a small one
    /// that trains on 2 CPU cores (the U-Net's 32/64/128, 16 DDIM steps).
    #[arg(long, value_enum, default_value_t = PresetArg::Cpu)]
    pub preset: PresetArg,
    /// Observation to condition on.
    #[arg(long, value_enum, default_value_t = PolicyObsArg::Keypoints)]
    pub obs: PolicyObsArg,
    /// Noise network: LeRobot's U-Net, or Diffusion Policy's transformer (the Diffusion
    /// Transformer: horizon 10 with images, 16 with keypoints; 2 observations, 8 executed).
    #[arg(long, value_enum, default_value_t = BackboneArg::Unet)]
    pub backbone: BackboneArg,
    /// With `--obs image`: also the wrist camera (`observation.images.wrist`, from `mte
    /// data generate --obs pixels,wrist`), its features beside the scene camera's in the
    /// conditioning. One encoder serves both (LeRobot's default); `--config` with
    /// `{"use_separate_rgb_encoder_per_camera": true}` gives each camera its own.
    #[arg(long)]
    pub wrist: bool,
    /// JSON file of config fields overriding the preset (LeRobot's config.json names),
    /// applied after `--backbone`'s settings: `{"transformer": {...}}` sets the Diffusion
    /// Transformer's width and depth.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Optimiser steps.
    #[arg(long, default_value_t = 20_000)]
    pub steps: usize,
    /// Batch size (windows).
    #[arg(long, default_value_t = 64)]
    pub batch_size: usize,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Checkpoint every this many steps.
    #[arg(long, default_value_t = 2_000)]
    pub checkpoint_every: usize,
    /// Start from these weights (a safetensors file with LeRobot keys, e.g. the
    /// encoder.safetensors of `mte train encoder`, or a model.safetensors); ignored on resume.
    #[arg(long, value_name = "FILE")]
    pub init: Option<PathBuf>,
    /// The n_obs_steps the --init weights were trained with, when fewer than this policy's
    /// (set by --config): the U-Net's conditioning columns for the older observations start
    /// at zero, so training starts from the init's policy exactly.
    #[arg(long, value_name = "N", requires = "init")]
    pub init_n_obs_steps: Option<usize>,
    /// Train only on the windows of successful episodes (e.g. corrective episodes in which
    /// the expert did not finish).
    #[arg(long)]
    pub successful_only: bool,
    /// Normalise with this checkpoint's statistics instead of the data's (for a warm start
    /// from it on data whose ranges differ, e.g. corrective episodes that leave the
    /// workspace: the network then sees its inputs and targets scaled as it was trained).
    #[arg(long, value_name = "DIR")]
    pub normalization_from: Option<PathBuf>,
    /// Keep the image encoder fixed and cache each frame's features (centre crop): a step
    /// then costs about what a keypoint policy's does.
    #[arg(long)]
    pub freeze_encoder: bool,
    /// Output directory; if it holds a training state, training resumes from it.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `mte sim ...`
#[derive(Debug, Subcommand)]
pub enum SimCommand {
    /// Render the reset state of a seed to a PNG.
    Render(SimRenderArgs),
    /// Run a policy for one or more episodes; optionally write an animated GIF.
    Rollout(SimRolloutArgs),
    /// Quick throughput check of the simulator (steps/s); the benchmark of record is
    /// `cargo bench -p mte-sim`.
    Bench(SimBenchArgs),
}

/// `mte data ...`
#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Generate scripted-expert demonstrations on PushT.
    Generate(DataGenerateArgs),
    /// Corrective demonstrations on PushT (DAgger's data): a policy drives each episode up
    /// to a random switch step, then the scripted expert takes over from the state the
    /// policy reached; only the expert's frames are recorded.
    Takeover(DataTakeoverArgs),
}

/// `mte data takeover`
#[derive(Debug, Args)]
pub struct DataTakeoverArgs {
    /// The policy that drives each episode before the switch (checkpoint directory).
    #[arg(long, value_name = "DIR")]
    pub checkpoint: PathBuf,
    /// The policy's arm: `open-loop`, or an aggregator text form (e.g. `ewm:0.01`).
    #[arg(long, default_value = "ewm:0.01", value_parser = arm)]
    pub execution: String,
    /// The policy's query stride (control steps).
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// Switch steps, drawn uniformly per episode: `FIRST..LAST` (control steps, both
    /// included, LAST below --max-steps).
    #[arg(long, default_value = "10..250", value_parser = step_range)]
    pub switch: (usize, usize),
    /// Number of episodes (those the policy finishes before its switch record nothing).
    #[arg(long, default_value_t = 100, value_parser = at_least_one)]
    pub episodes: usize,
    /// Base seed: episode i resets with seed + i (keep clear of the test seeds
    /// 100000-100049 and the validation seeds 200000-200049).
    #[arg(long, default_value_t = 300_000)]
    pub seed: u64,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// Observations to record besides the agent position: comma-separated subset of
    /// state, keypoints, pixels.
    #[arg(long, default_value = "state,keypoints")]
    pub obs: mte_data::ObsSet,
    /// Side of recorded frames (px).
    #[arg(long, default_value_t = 96)]
    pub image_size: usize,
    /// Step limit per episode (the policy's part included).
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
    /// The expert's travel step (px), as for the demonstrations.
    #[arg(long, default_value_t = ExpertConfig::default().travel_step)]
    pub travel_step: f64,
    /// The expert's push step (px), as for the demonstrations.
    #[arg(long, default_value_t = ExpertConfig::default().push_step)]
    pub push_step: f64,
    /// Let the expert's first plan continue a push it finds the agent inside (otherwise it
    /// backs out to approach again, as the demonstrating expert would plan from there).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub resume_pushes: bool,
    /// Seed of the policy's sampling noise.
    #[arg(long, default_value_t = 0)]
    pub noise_seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Output directory (must not already hold a dataset).
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `FIRST..LAST`, both included.
fn step_range(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| format!("{s:?}: expected FIRST..LAST, e.g. 10..250"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|e| format!("{v:?} in {s:?}: {e}"))
    };
    let (a, b) = (parse(a)?, parse(b)?);
    if a > b {
        return Err(format!("{s:?}: FIRST must not exceed LAST"));
    }
    Ok((a, b))
}

/// Which random stream a seeded reset draws from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum StreamArg {
    /// numpy RandomState(seed): Diffusion Policy and gym-pusht <= 0.1.5.
    Legacy,
    /// gymnasium's PCG64 Generator: gym-pusht >= 0.1.6.
    Pcg64,
}

impl From<StreamArg> for mte_sim::ResetStream {
    fn from(s: StreamArg) -> Self {
        match s {
            StreamArg::Legacy => mte_sim::ResetStream::Legacy,
            StreamArg::Pcg64 => mte_sim::ResetStream::Pcg64,
        }
    }
}

/// `mte sim render`
#[derive(Debug, Args)]
pub struct SimRenderArgs {
    /// Reset seed.
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// Output side in px: 96 is the policy's observation; larger sizes are visualisations.
    #[arg(long, default_value_t = 96)]
    pub size: usize,
    /// Draw the visualisation frame (gym-pusht's `render()`) instead of the observation.
    #[arg(long)]
    pub vis: bool,
    /// Output PNG file.
    #[arg(long, short, value_name = "FILE")]
    pub out: PathBuf,
}

/// Policies the simulator can roll out on its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SimPolicy {
    /// The scripted push-primitive MPC expert.
    Expert,
    /// Uniform random targets in [0, 512]^2 (the peer benchmark's workload).
    Random,
}

/// `mte sim rollout`
#[derive(Debug, Args)]
pub struct SimRolloutArgs {
    /// Policy to run.
    #[arg(long, value_enum, default_value_t = SimPolicy::Expert)]
    pub policy: SimPolicy,
    /// First reset seed; episode i uses seed + i.
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Number of episodes.
    #[arg(long, default_value_t = 1, value_parser = at_least_one)]
    pub episodes: usize,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// Step limit per episode (gym-pusht: 300).
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
    /// Write the first episode as an animated GIF (10 frames/s, with the action marker).
    #[arg(long, value_name = "FILE")]
    pub gif: Option<PathBuf>,
    /// Side of the GIF frames (px).
    #[arg(long, default_value_t = 256)]
    pub gif_size: usize,
}

/// `mte sim bench`
#[derive(Debug, Args)]
pub struct SimBenchArgs {
    /// Control steps to time per observation kind.
    #[arg(long, default_value_t = 20_000)]
    pub steps: usize,
}

/// `mte data generate`
#[derive(Debug, Args)]
pub struct DataGenerateArgs {
    /// Where the demonstrations come from: `pusht` (the native simulator and its scripted
    /// expert), or a bridge target with a scripted expert, `robomimic:lift|can|square`
    /// (recorded: the 9-D proprioception, the task's object-state, 7-D OSC_POSE actions,
    /// with `--obs pixels` the 84 x 84 agentview frame as `observation.image`, with
    /// `--obs pixels,wrist` the eye-in-hand camera's too as `observation.images.wrist`; give
    /// `--image-size 84` and `--max-steps 400`; only successful episodes are kept unless
    /// `--keep-failures`).
    #[arg(long, default_value = "pusht")]
    pub env: mte_eval::environment::EnvTarget,
    /// Bridge targets: keep failed expert episodes too.
    #[arg(long)]
    pub keep_failures: bool,
    /// Number of episodes.
    #[arg(long, default_value_t = 100, value_parser = at_least_one)]
    pub episodes: usize,
    /// Base seed: episode i resets with seed + i (keep clear of the test seeds
    /// 100000-100049).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// Observations to record besides the agent position: comma-separated subset of
    /// state, keypoints, pixels, wrist (the wrist camera: robomimic targets only).
    #[arg(long, default_value = "state,keypoints")]
    pub obs: mte_data::ObsSet,
    /// Side of recorded frames (px).
    #[arg(long, default_value_t = 96)]
    pub image_size: usize,
    /// Step limit per episode.
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
    /// Uniform noise added to the expert's targets (px), for more varied demonstrations.
    #[arg(long, default_value_t = 0.0)]
    pub action_noise: f64,
    /// Largest target displacement per control step while the expert travels around the
    /// block (px). Smaller values give slower, smoother demonstrations that are easier to
    /// imitate.
    #[arg(long, default_value_t = ExpertConfig::default().travel_step)]
    pub travel_step: f64,
    /// Target displacement per control step while the expert pushes (px).
    #[arg(long, default_value_t = ExpertConfig::default().push_step)]
    pub push_step: f64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Output directory (must not already hold a dataset).
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `mte ensemble ...`
#[derive(Debug, Subcommand)]
pub enum EnsembleCommand {
    /// Aggregate a recorded chunk stream (JSON Lines) and write one line per control time.
    Replay(ReplayArgs),
}

/// `mte synthetic`
#[derive(Debug, Args)]
pub struct SyntheticArgs {
    /// Episodes per burst length q.
    #[arg(long, default_value_t = 20, value_parser = at_least_one)]
    pub episodes: usize,
    /// Control steps per episode.
    #[arg(long, default_value_t = 300)]
    pub steps: u64,
    /// Burst lengths: corrupted queries per period of M_min queries (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
    pub q: Vec<usize>,
    /// Aggregators to compare (comma-separated text forms; the first is the baseline of
    /// the paired tests), e.g. `ewm:0.01,median,trimmed-mean:2`.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "ewm:0.01,median,median:drop-oldest,trimmed-mean:2,medoid"
    )]
    pub aggregators: Vec<Aggregator>,
    /// Prediction horizon T_p (rows per chunk).
    #[arg(long, default_value_t = 16)]
    pub t_p: usize,
    /// Observation steps T_o (the executable part of a chunk starts at row T_o - 1).
    #[arg(long, default_value_t = 2)]
    pub t_o: usize,
    /// Stride h: control steps between queries.
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// Action dimension.
    #[arg(long, default_value_t = 2)]
    pub dim: usize,
    /// Standard deviation of a clean prediction's error (action units, PushT pixels).
    #[arg(long, default_value_t = 2.0)]
    pub noise: f64,
    /// Displacement of corrupted chunks (action units).
    #[arg(long, default_value_t = 100.0)]
    pub corruption: f64,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the full report as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// `mte ensemble replay`
#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// Chunk stream, JSON Lines (`{"t": 0, "chunk": [[...], ...], "corrupted": false}`);
    /// `-` reads standard input.
    pub file: PathBuf,
    /// Aggregator text form, e.g. `median`, `ewm:0.01`, `trimmed-medoid:2`.
    #[arg(long, short, default_value = "ewm:0.01")]
    pub aggregator: Aggregator,
    /// Observation steps T_o of the policy that wrote the chunks: row T_o - 1 is the
    /// action for the query's own time step (1 for ACT, 2 for Diffusion Policy).
    #[arg(long, default_value_t = 1)]
    pub t_o: usize,
    /// Write the executed actions here (JSON Lines) instead of stdout; written to a
    /// temporary file and renamed, so a failed run leaves no partial file.
    #[arg(long, short, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// `mte demo`
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Paired episodes per cell (seeds 100000, 100001, ...: Diffusion Policy's test seeds).
    #[arg(long, default_value_t = 20, value_parser = at_least_one)]
    pub episodes: usize,
    /// Policy checkpoint directory (default: the bundled keypoint policy).
    #[arg(long, value_name = "DIR")]
    pub policy: Option<PathBuf>,
    /// Arms compared on the same episodes (comma-separated; the first is the baseline).
    #[arg(long, value_delimiter = ',', default_value = "ewm:0.01,median", value_parser = arm)]
    pub aggregators: Vec<String>,
    /// Corruption at struck queries, as TOML inline table fields, e.g. `kind = "blank"`,
    /// `kind = "occluder", size = 24`, `kind = "gaussian-noise", sigma = 20.0`.
    #[arg(long, default_value = r#"kind = "blank""#, value_parser = fault)]
    pub fault: mte_eval::corruption::Fault,
    /// Burst lengths q (corrupted queries per period of M_min); 0 is the clean cell.
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
    pub q: Vec<usize>,
    /// Query stride h.
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Episodes of a cell run in lockstep, the policy answering their queries in one batch
    /// (the records do not depend on it); 1 runs each episode alone.
    #[arg(long, default_value_t = mte_eval::sweep::RunOptions::DEFAULT_BATCH, value_parser = at_least_one)]
    pub batch: usize,
    /// Run directory; an existing run of the same grid is resumed.
    #[arg(long, short, value_name = "DIR", default_value = "runs/demo")]
    pub out: PathBuf,
}

/// `mte film`
#[derive(Debug, Args)]
pub struct FilmArgs {
    /// Policy checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Reset seed.
    #[arg(long, default_value_t = 100_000)]
    pub seed: u64,
    /// Reset stream.
    #[arg(long, value_enum, default_value_t = StreamArg::Legacy)]
    pub stream: StreamArg,
    /// The two arms, left then right (comma-separated).
    #[arg(long, value_delimiter = ',', num_args = 1, default_value = "ewm:0.01,median", value_parser = arm)]
    pub arms: Vec<String>,
    /// Corruption at struck queries, as TOML inline table fields (as `mte demo --fault`).
    #[arg(long, default_value = r#"kind = "blank""#, value_parser = fault)]
    pub fault: mte_eval::corruption::Fault,
    /// Burst length q (corrupted queries per period of M_min); 0 films a clean episode.
    #[arg(long, default_value_t = 2)]
    pub q: usize,
    /// Query stride h.
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// Step limit.
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
    /// Seed of the sampling and corruption streams (a sweep's `noise_seed`).
    #[arg(long, default_value_t = 0)]
    pub noise_seed: u64,
    /// Panel side in pixels (32..=1024).
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Directory for figure2.gif and figure2-strip.png.
    #[arg(long, short, value_name = "DIR", default_value = "runs/film")]
    pub out: PathBuf,
}

/// `mte sweep`
#[derive(Debug, Args)]
pub struct SweepArgs {
    /// Sweep spec (TOML; see `mte_eval::sweep`).
    pub spec: PathBuf,
    /// Run directory.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
    /// Continue a run in `--out`: finished episodes are skipped. The spec may append seeds to
    /// every cell (raise `count`) to grow a finished run to a larger n, and may add cells (a
    /// new `q`, a new corruption); the stored cells must stay as they were.
    #[arg(long)]
    pub resume: bool,
    /// Run only shard `i/n` of the cells (e.g. a Slurm array index); shards may share `--out`.
    #[arg(long, default_value = "0/1")]
    pub shard: mte_eval::sweep::Shard,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Episodes of a cell run in lockstep, the policy answering their queries in one batch
    /// (the records do not depend on it); 1 runs each episode alone.
    #[arg(long, default_value_t = mte_eval::sweep::RunOptions::DEFAULT_BATCH, value_parser = at_least_one)]
    pub batch: usize,
    /// Where the policies run: `cpu`, or `cuda` / `cuda:N` in a build with the `cuda`
    /// feature (environments and ensemblers stay on the CPU).
    #[arg(long, default_value = "cpu")]
    pub device: mte_policy::ComputeDevice,
}

/// `mte report`
#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Run directories (shards of one grid are merged).
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Where to write report.md, report.html and plots/ (default: the first run directory).
    #[arg(long, short, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Baseline arm of the paired tests (default: the first `ewm` arm).
    #[arg(long)]
    pub baseline: Option<String>,
    /// Robust arm (default: `median`).
    #[arg(long)]
    pub robust: Option<String>,
    /// Cell of the aggregator table (default: the corrupted cell with most arms).
    #[arg(long)]
    pub cell: Option<String>,
    /// Report only these cells (repeatable; name the clean cells the others are read
    /// against too): the tables, plots and the multiple-test corrections then count them
    /// alone, e.g. when a run directory merged for its clean cell holds other experiments.
    #[arg(long, value_name = "CELL")]
    pub only: Vec<String>,
    /// Add the defence table: `UNDEFENDED:DEFENDED` policies (paths however spelled, so
    /// `./p` and `sweeps/../p` name `p`, or their last component), cells paired by
    /// corruption and h.
    #[arg(long, value_name = "UNDEFENDED:DEFENDED", value_parser = parse_defence)]
    pub defence: Option<mte_eval::report::DefencePair>,
    /// Add the control table: the cell `ATTACK` read against the cell `CONTROL` per arm
    /// (e.g. an adversarial patch against a grey square, PGD against random noise of its
    /// radius); repeatable. Cells of merged runs pair by seed.
    #[arg(long, value_name = "ATTACK:CONTROL", value_parser = parse_control)]
    pub control: Vec<mte_eval::report::ControlPair>,
    /// McNemar test on paired success: `exact` (default) or `chi2-cc` (chi-square with
    /// continuity correction).
    #[arg(long, default_value = "exact")]
    pub mcnemar: mte_eval::report::McNemarTest,
    /// Film Figure 2 (the chosen episode with both arms, as a GIF and a strip of frames)
    /// into the report; runs the policy of the chosen cell twice.
    #[arg(long)]
    pub figure2: bool,
}

fn parse_control(s: &str) -> Result<mte_eval::report::ControlPair, String> {
    match s.split_once(':') {
        Some((a, c)) if !a.is_empty() && !c.is_empty() && !c.contains(':') => {
            Ok(mte_eval::report::ControlPair {
                attack: a.to_string(),
                control: c.to_string(),
            })
        }
        _ => Err(format!(
            "`{s}`: expected ATTACK:CONTROL, two cell ids separated by one colon"
        )),
    }
}

fn parse_defence(s: &str) -> Result<mte_eval::report::DefencePair, String> {
    match s.rsplit_once(':') {
        Some((u, d)) if !u.is_empty() && !d.is_empty() => Ok(mte_eval::report::DefencePair {
            undefended: u.to_string(),
            defended: d.to_string(),
        }),
        _ => Err(format!(
            "`{s}`: expected UNDEFENDED:DEFENDED, two policy names separated by a colon"
        )),
    }
}

/// `mte attack ...`
#[derive(Debug, Subcommand)]
pub enum AttackCommand {
    /// Sweep PGD's budget and step size against the undefended arm until the attack stops
    /// improving (the paper's calibration).
    Calibrate(CalibrateArgs),
    /// Train a physical patch against an image policy on demonstration windows (writes
    /// patch.png + patch.json; evaluate it with `fault = { kind = "patch", path = ... }`).
    Patch(AttackPatchArgs),
    /// Make a control of a trained patch: the same square at the same place, filled with the
    /// patch's mean colour, mid-grey or seeded noise (evaluate it beside the patch: the
    /// patch's effect beyond it is its pattern's, not the occlusion's).
    Control(AttackControlArgs),
    /// How aligned a corruption's displacements are across the candidates covering a control
    /// time (median pairwise cosine of corrupted-minus-clean candidate rows, the clean twin
    /// drawn with the executed chunk's noise): 1 is common-mode. PGD, blank frames or a patch.
    Alignment(AlignmentArgs),
    /// How many camera frames give pixel PGD a gradient at all: per frame of a dataset, the
    /// image encoder's features that are non-zero after its final ReLU (a frame with none has
    /// an exactly zero pixel gradient), and the query windows whose every frame has none.
    Activity(ActivityArgs),
}

/// `mte attack activity`
#[derive(Debug, Args)]
pub struct ActivityArgs {
    /// Image Diffusion Policy checkpoint directory (one camera).
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Dataset directory with the policy's camera frames (`mte data generate --obs pixels`).
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Half-width of uniform noise added to every pixel first (pixels in [0, 1]), as PGD's
    /// random start draws it; repeat for several (0 is the clean frames).
    #[arg(long, default_values_t = [0.0f32])]
    pub eps: Vec<f32>,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames encoded per forward pass.
    #[arg(long, default_value_t = 64, value_parser = at_least_one)]
    pub batch: usize,
}

/// The corruption `mte attack alignment` measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AlignmentFault {
    /// PGD on the observation (`--iterations`, `--eps`).
    Pgd,
    /// Blank frames (zero pixels, or zero keypoints).
    Blank,
    /// A trained patch (`--patch DIR`) drawn into the camera frames.
    Patch,
}

/// `mte attack alignment`
#[derive(Debug, Args)]
pub struct AlignmentArgs {
    /// Policy checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Episodes (seeds 100000, ...).
    #[arg(long, default_value_t = 10, value_parser = at_least_one)]
    pub episodes: usize,
    /// The corruption of the corrupted queries.
    #[arg(long, value_enum, default_value_t = AlignmentFault::Pgd)]
    pub fault: AlignmentFault,
    /// The patch directory (`mte attack patch` or `mte attack control`), with `--fault patch`.
    #[arg(long, value_name = "DIR", required_if_eq("fault", "patch"))]
    pub patch: Option<PathBuf>,
    /// PGD iterations.
    #[arg(long, default_value_t = 10, value_parser = at_least_one)]
    pub iterations: usize,
    /// L-infinity radius (pixels in [0, 1], or normalised keypoints).
    #[arg(long, default_value_t = 0.03)]
    pub eps: f64,
    /// Burst length q (corrupted queries per M_min).
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub q: usize,
    /// Query stride h.
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// The arm that executes.
    #[arg(long, default_value = "ewm:0.01", value_parser = arm)]
    pub arm: String,
    /// Step limit per episode.
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
}

/// `mte monitor ...`
#[derive(Debug, Subcommand)]
pub enum MonitorCommand {
    /// Thresholds from the clean episodes of a run recorded with monitors, by each monitor's
    /// own rule (TIDE: split conformal at alpha 0.001 over pooled query scores; ACC: the
    /// ceil((n+1)(1-delta))-th largest episode maximum, delta 0.05); writes a JSON file a
    /// control loop can load.
    Calibrate(MonitorCalibrateArgs),
    /// Firing rate, first alarm and AUROC (against the clean cell of the same stride) of
    /// every cell and arm of a run, with thresholds from `mte monitor calibrate`.
    Evaluate(MonitorEvaluateArgs),
}

/// `mte monitor calibrate`
#[derive(Debug, Args)]
pub struct MonitorCalibrateArgs {
    /// Run directory holding the clean calibration cell.
    pub run: PathBuf,
    /// The clean cell (default: the run's only clean cell).
    #[arg(long)]
    pub cell: Option<String>,
    /// The arm whose episodes calibrate.
    #[arg(long, default_value = "ewm:0.01")]
    pub arm: String,
    /// Calibrate on every episode, not only the successful ones.
    #[arg(long)]
    pub all_episodes: bool,
    /// TIDE over each episode's maximum instead of pooled query scores (then at alpha 0.001
    /// fewer than 999 episodes give a threshold that can never fire).
    #[arg(long)]
    pub tide_episode_max: bool,
    /// TIDE's alpha.
    #[arg(long, default_value_t = 0.001)]
    pub alpha: f64,
    /// ACC's delta.
    #[arg(long, default_value_t = 0.05)]
    pub delta: f64,
    /// Where to write the thresholds (JSON).
    #[arg(long, short, value_name = "FILE")]
    pub out: PathBuf,
}

/// `mte monitor evaluate`
#[derive(Debug, Args)]
pub struct MonitorEvaluateArgs {
    /// Run directory recorded with monitors.
    pub run: PathBuf,
    /// Thresholds from `mte monitor calibrate` (on other episodes than these).
    #[arg(long, value_name = "FILE")]
    pub thresholds: PathBuf,
    /// Also write ROC plots (`roc-<monitor>-<arm>.svg`, one curve per corrupted cell against
    /// its clean cell) into this folder.
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
}

/// `mte attack control`
#[derive(Debug, Args)]
pub struct AttackControlArgs {
    /// The trained patch directory (patch.png + patch.json).
    #[arg(long, value_name = "DIR")]
    pub patch: PathBuf,
    /// Where to write the control patch directory.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
    /// What fills the square.
    #[arg(long, value_enum, default_value_t = ControlArg::MeanColour)]
    pub kind: ControlArg,
    /// Seed of the noise control.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// The control texture of `mte attack control`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ControlArg {
    /// The patch's mean colour.
    MeanColour,
    /// Mid-grey (128, 128, 128).
    Grey,
    /// Uniform random bytes (seeded).
    Noise,
}

/// Where patch training places the texture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum PlacementArg {
    /// Every batch at `--center`.
    Fixed,
    /// Each batch at a position drawn uniformly inside the policy's evaluation crop, the
    /// texture's centre at least `--min-goal-distance` from the goal's centre.
    AwayFromGoal,
}

/// Patch ascent rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum AscentArg {
    /// P += step * sign(gradient).
    Sign,
    /// P += step * gradient.
    Raw,
}

/// `mte attack patch`
#[derive(Debug, Args)]
pub struct AttackPatchArgs {
    /// Image-policy checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Dataset directory with images (`mte data generate --obs state,keypoints,pixels`).
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Texture side (observation px).
    #[arg(long, default_value_t = 16)]
    pub side: usize,
    /// Centre in world px (512 x 512), "x,y": where the patch is evaluated (and trained, with
    /// `--placement fixed`). The default lies away from the goal, inside the camera crop.
    #[arg(long, default_value = "112,112", value_parser = world_point)]
    pub center: [f64; 2],
    /// Where training places the texture in each batch.
    #[arg(long, value_enum, default_value_t = PlacementArg::AwayFromGoal)]
    pub placement: PlacementArg,
    /// Least distance of the texture's centre from the goal's centre (world px) under
    /// `--placement away-from-goal`.
    #[arg(long, default_value_t = 150.0)]
    pub min_goal_distance: f64,
    /// Epochs (the protocol: 11).
    #[arg(long, default_value_t = 11)]
    pub epochs: usize,
    /// Batches per epoch.
    #[arg(long, default_value_t = 16)]
    pub batches_per_epoch: usize,
    /// Windows per batch.
    #[arg(long, default_value_t = 16)]
    pub batch_size: usize,
    /// Step size (the protocol's grid: 1e-4, 5e-4, 1.5e-3, 5e-3).
    #[arg(long, default_value_t = 1.5e-3)]
    pub step: f64,
    /// Ascent rule.
    #[arg(long, value_enum, default_value_t = AscentArg::Sign)]
    pub ascent: AscentArg,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `mte defend ...`
#[derive(Debug, Subcommand)]
pub enum DefendCommand {
    /// Encoder adversarial fine-tuning against a patch (denoising head frozen).
    Finetune(FinetuneArgs),
    /// Gradient probe: original vs fine-tuned encoder.
    Probe(ProbeArgs),
}

/// Consistency anchor of `mte defend finetune`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AnchorArg {
    /// The encoder before fine-tuning (frozen copy).
    Original,
    /// The encoder being fine-tuned (detached).
    Current,
}

/// `mte defend finetune`
#[derive(Debug, Args)]
pub struct FinetuneArgs {
    /// Image-policy checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Dataset directory with images.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Patch directory (`mte attack patch`).
    #[arg(long, value_name = "DIR")]
    pub patch: PathBuf,
    /// Steps (the protocol: 3000).
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Learning rate (the protocol: 1e-5).
    #[arg(long, default_value_t = 1e-5)]
    pub lr: f64,
    /// Consistency weight.
    #[arg(long, default_value_t = 1.0)]
    pub consistency: f64,
    /// Clean embedding the consistency term ties the patched one to.
    #[arg(long, value_enum, default_value_t = AnchorArg::Original)]
    pub anchor: AnchorArg,
    /// Weight of the clean-feature term: the tuned encoder's embedding of the clean frames
    /// tied to the original encoder's (an mte extension; 0, the protocol, leaves it off).
    #[arg(long, default_value_t = 0.0)]
    pub clean_features: f64,
    /// Weight of the clean task term: the frozen head's denoising loss on the clean frames,
    /// beside the patched ones (an mte extension; 0, the protocol, leaves it off).
    #[arg(long, default_value_t = 0.0)]
    pub clean_task: f64,
    /// Windows per batch.
    #[arg(long, default_value_t = 16)]
    pub batch_size: usize,
    /// Regenerate the patch against the current encoder every step; the final patch is
    /// saved as `OUT/patch` (a patch directory, as `mte attack patch` writes).
    #[arg(long)]
    pub regenerate: bool,
    /// Sign-ascent step of the regeneration (pixel values in [0, 1]; requires --regenerate).
    #[arg(
        long,
        value_name = "STEP",
        requires = "regenerate",
        default_value_t = 1.5e-3
    )]
    pub regenerate_step: f64,
    /// Also save the policy every N steps, as `OUT/step-N` (for the clean-cost curve).
    #[arg(long, value_name = "N")]
    pub checkpoint_every: Option<usize>,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output checkpoint directory.
    #[arg(long, short, value_name = "DIR")]
    pub out: PathBuf,
}

/// `mte defend probe`
#[derive(Debug, Args)]
pub struct ProbeArgs {
    /// Original checkpoint.
    #[arg(long, value_name = "DIR")]
    pub original: PathBuf,
    /// Fine-tuned checkpoint.
    #[arg(long, value_name = "DIR")]
    pub tuned: PathBuf,
    /// Dataset directory with images.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Patch directory.
    #[arg(long, value_name = "DIR")]
    pub patch: PathBuf,
    /// Batches.
    #[arg(long, default_value_t = 4)]
    pub batches: usize,
    /// Windows per batch.
    #[arg(long, default_value_t = 8)]
    pub batch_size: usize,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `mte attack calibrate`
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// Policy checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Paired episodes per point (seeds 100000, ...).
    #[arg(long, default_value_t = 10, value_parser = at_least_one)]
    pub episodes: usize,
    /// Budgets (iterations), tried in increasing order.
    #[arg(long, value_delimiter = ',', default_value = "5,20,50,200,500")]
    pub iterations: Vec<usize>,
    /// Step sizes.
    #[arg(long, value_delimiter = ',', default_value = "0.001875")]
    pub steps: Vec<f64>,
    /// L-infinity radius (pixels in [0, 1], or normalised keypoints).
    #[arg(long, default_value_t = 0.03)]
    pub eps: f64,
    /// Undefended arm.
    #[arg(long, default_value = "ewm:0.01", value_parser = arm)]
    pub arm: String,
    /// Burst length q.
    #[arg(long, default_value_t = 2)]
    pub q: usize,
    /// Query stride h.
    #[arg(long, default_value_t = 2, value_parser = at_least_one)]
    pub stride: usize,
    /// Stop a step size when a larger budget lowers mean coverage by less than this.
    #[arg(long, default_value_t = 0.01)]
    pub tolerance: f64,
    /// Step limit per episode.
    #[arg(long, default_value_t = 300, value_parser = at_least_one)]
    pub max_steps: usize,
}

/// A count that must be positive (episodes, steps, strides): rejected at parse time.
fn at_least_one(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("0: expected an integer >= 1".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(format!("{s:?}: expected an integer >= 1 ({e})")),
    }
}

/// An arm: `open-loop` or an aggregator's text form, checked at parse time and kept as typed
/// (run files name arms by their text).
fn arm(s: &str) -> Result<String, String> {
    s.parse::<mte_eval::pusht::Execution>()
        .map(|_| s.trim().to_string())
        .map_err(|e| format!("{s:?}: expected open-loop or an aggregator ({e})"))
}

/// A fault as TOML inline-table fields (`kind = "occluder", size = 24`).
fn fault(s: &str) -> Result<mte_eval::corruption::Fault, String> {
    let f: mte_eval::corruption::Fault = toml::from_str(s)
        .map_err(|e| format!("{s:?}: expected fault fields such as kind = \"blank\" ({e})"))?;
    f.validate().map_err(|e| e.to_string())?;
    Ok(f)
}

/// A point of the 512 x 512 world, `"x,y"` in px.
fn world_point(s: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: expected \"x,y\" in world px ({e})"))?;
    match v[..] {
        [x, y] if x.is_finite() && y.is_finite() => Ok([x, y]),
        _ => Err(format!(
            "{s:?}: expected two finite numbers \"x,y\" in world px"
        )),
    }
}

/// `WxH` in pixels.
fn size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("{s:?}: expected WxH, e.g. 84x84"))?;
    let parse = |v: &str| {
        v.parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("{s:?}: expected WxH with positive integers"))
    };
    Ok((parse(w)?, parse(h)?))
}
