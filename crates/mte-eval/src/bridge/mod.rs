//! The environment bridge: an [`Environment`] that lives in a worker process.
//!
//! [`BridgeEnv`] starts the Python worker shipped with mte (`worker.py`, embedded in the
//! binary and run with `python -u -c`), and talks to it over its standard streams in the
//! framed format of [`frame`]: one request, one response, a JSON header plus raw arrays.
//! The worker hosts one environment named by a [`Target`]: any gymnasium environment
//! (`gym:gym_pusht/PushT-v0`), robosuite as robomimic configures it (`robomimic:can`), or a
//! pure-Python toy used by the tests.
//!
//! Failures are typed ([`BridgeError`] inside [`EnvError::Bridge`]) and carry the tail of
//! the worker's stderr: a worker that exits is [`BridgeError::Exited`], one that does not
//! answer within the timeout is killed and reported as [`BridgeError::Hung`], a request the
//! worker refuses is [`BridgeError::Refused`]. The runner records such an episode as failed
//! with that message and goes on.
//!
//! Which Python runs the worker: [`BridgeOptions::python`], else the `MTE_PYTHON`
//! environment variable, else the target's own environment made by `tools/env-setup`
//! (`target/envs/<name>/bin/python` under the working directory; a missing one is
//! [`BridgeError::NotSetUp`] naming the setup command), else `python3`.

pub mod expert;
pub mod frame;

pub use expert::{ExpertEpisode, run_expert};

use std::fmt;
use std::io::{BufRead, BufReader, Read};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::str::FromStr;
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use mte_policy::{ObsNeeds, Observation};
use serde_json::{Value, json};

use self::frame::{ArrayData, Frame, FrameError, read_frame, write_frame};
use crate::environment::{EnvError, Environment, Outcome};

/// The worker's source, shipped inside the binary.
pub const WORKER_SOURCE: &str = include_str!("worker.py");
/// The protocol version this side speaks.
pub const PROTOCOL: u64 = 1;
/// Bytes of the worker's stderr kept for error reports.
const STDERR_TAIL: usize = 8 * 1024;

/// A robomimic task (robosuite environment, as robomimic and Diffusion Policy set it up).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RobomimicTask {
    /// `Lift`: raise the cube.
    Lift,
    /// `PickPlaceCan`: put the can in its bin.
    Can,
    /// `NutAssemblySquare`: put the square nut on its peg.
    Square,
}

impl RobomimicTask {
    /// All three, in the paper's order.
    pub const ALL: [RobomimicTask; 3] = [Self::Lift, Self::Can, Self::Square];

    /// The name in targets (`lift`, `can`, `square`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Lift => "lift",
            Self::Can => "can",
            Self::Square => "square",
        }
    }
}

/// What a bridge worker hosts.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum Target {
    /// `toy:<options>`: the worker's pure-Python 1-D point (tests; options `crash-at=N`,
    /// `hang-at=N`).
    Toy(String),
    /// `gym:<module>/<EnvId>[?key=value&...]`: a gymnasium environment.
    Gym {
        /// Module imported first (it registers the id).
        module: String,
        /// The gymnasium id.
        id: String,
        /// `key=value&...` keyword arguments of `gymnasium.make`, as written.
        kwargs: String,
    },
    /// `robomimic:<task>`.
    Robomimic(RobomimicTask),
}

/// A bridge target that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "environment target {0:?}: expected pusht, gym:<module>/<EnvId>[?key=value&...], robomimic:lift|can|square or toy:"
)]
pub struct TargetError(pub String);

impl FromStr for Target {
    type Err = TargetError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || TargetError(s.to_string());
        let (kind, rest) = s.split_once(':').ok_or_else(bad)?;
        match kind {
            "toy" => Ok(Target::Toy(rest.into())),
            "gym" => {
                let (path, kwargs) = rest.split_once('?').unwrap_or((rest, ""));
                let (module, id) = path.rsplit_once('/').ok_or_else(bad)?;
                if module.is_empty() || id.is_empty() {
                    return Err(bad());
                }
                Ok(Target::Gym {
                    module: module.into(),
                    id: id.into(),
                    kwargs: kwargs.into(),
                })
            }
            "robomimic" => RobomimicTask::ALL
                .into_iter()
                .find(|t| t.as_str() == rest)
                .map(Target::Robomimic)
                .ok_or_else(bad),
            _ => Err(bad()),
        }
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Target::Toy(o) => write!(f, "toy:{o}"),
            Target::Gym { module, id, kwargs } if kwargs.is_empty() => {
                write!(f, "gym:{module}/{id}")
            }
            Target::Gym { module, id, kwargs } => write!(f, "gym:{module}/{id}?{kwargs}"),
            Target::Robomimic(t) => write!(f, "robomimic:{}", t.as_str()),
        }
    }
}

impl Target {
    /// The virtual environment `tools/env-setup` makes for this target, if it needs one.
    pub fn setup_name(&self) -> Option<&'static str> {
        match self {
            Target::Robomimic(_) => Some("robomimic"),
            _ => None,
        }
    }
}

/// A failure of the bridge.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BridgeError {
    /// The worker's Python could not be started.
    #[error("starting the bridge worker with {python}: {error}")]
    Spawn {
        /// The interpreter.
        python: String,
        /// Why.
        error: String,
    },
    /// The target's environment was never set up.
    #[error(
        "{target} needs its Python environment, which is missing ({python} not found): run `{command}` from the repository root, or set MTE_PYTHON"
    )]
    NotSetUp {
        /// The target.
        target: String,
        /// The interpreter looked for.
        python: String,
        /// The setup command.
        command: String,
    },
    /// The worker exited (or closed its stdout) before answering.
    #[error(
        "bridge worker for {target} exited during `{op}` ({status}); its stderr ends:\n{stderr}"
    )]
    Exited {
        /// The target.
        target: String,
        /// The request in flight.
        op: String,
        /// Exit status, as the OS reports it.
        status: String,
        /// The tail of its stderr.
        stderr: String,
    },
    /// The worker did not answer in time and was killed.
    #[error(
        "bridge worker for {target} did not answer `{op}` within {seconds} s and was killed; its stderr ends:\n{stderr}"
    )]
    Hung {
        /// The target.
        target: String,
        /// The request in flight.
        op: String,
        /// The timeout (s).
        seconds: f64,
        /// The tail of its stderr.
        stderr: String,
    },
    /// The worker answered with an error.
    #[error("bridge worker for {target} refused `{op}`: {message}")]
    Refused {
        /// The target.
        target: String,
        /// The request.
        op: String,
        /// The worker's message.
        message: String,
    },
    /// The worker spoke out of protocol.
    #[error("bridge worker for {target}, `{op}`: {error}")]
    Protocol {
        /// The target.
        target: String,
        /// The request.
        op: String,
        /// What was wrong.
        error: String,
    },
}

/// How a [`BridgeEnv`] starts and waits for its worker.
#[derive(Clone, Debug, PartialEq)]
pub struct BridgeOptions {
    /// The Python interpreter (see the module docs for the default).
    pub python: Option<PathBuf>,
    /// How long one request may take before the worker counts as hung (s).
    pub timeout_s: f64,
    /// How long building the environment (`hello`) may take (s): simulators load models.
    pub startup_timeout_s: f64,
}

impl Default for BridgeOptions {
    fn default() -> Self {
        Self {
            python: None,
            // A robosuite step with a camera takes ~0.1 s, a reset a few seconds; 120 s
            // only fires on a worker that is stuck.
            timeout_s: 120.0,
            startup_timeout_s: 600.0,
        }
    }
}

impl BridgeOptions {
    /// The interpreter for `target` (see the module docs), environments made by
    /// `tools/env-setup` looked for under the working directory.
    pub fn interpreter(&self, target: &Target) -> Result<PathBuf, BridgeError> {
        let cwd = std::env::current_dir().unwrap_or_default();
        self.interpreter_in(target, std::env::var_os("MTE_PYTHON"), &cwd)
    }

    /// [`Self::interpreter`] with `MTE_PYTHON`'s value and the repository root given.
    pub fn interpreter_in(
        &self,
        target: &Target,
        env_python: Option<std::ffi::OsString>,
        root: &std::path::Path,
    ) -> Result<PathBuf, BridgeError> {
        if let Some(p) = &self.python {
            return Ok(p.clone());
        }
        if let Some(p) = env_python.filter(|p| !p.is_empty()) {
            return Ok(PathBuf::from(p));
        }
        if let Some(name) = target.setup_name() {
            let p = root.join(format!("target/envs/{name}/bin/python"));
            if !p.exists() {
                return Err(BridgeError::NotSetUp {
                    target: target.to_string(),
                    python: p.display().to_string(),
                    command: format!("tools/env-setup {name}"),
                });
            }
            return Ok(p);
        }
        Ok(PathBuf::from("python3"))
    }
}

/// The last [`STDERR_TAIL`] bytes a worker wrote to stderr.
#[derive(Default)]
struct Tail(Vec<u8>);

impl Tail {
    fn push(&mut self, line: &[u8]) {
        self.0.extend_from_slice(line);
        if self.0.len() > STDERR_TAIL {
            let cut = self.0.len() - STDERR_TAIL;
            self.0.drain(..cut);
        }
    }
}

/// An environment in a worker process (see the module docs).
pub struct BridgeEnv {
    target: Target,
    options: BridgeOptions,
    child: Child,
    stdin: Option<ChildStdin>,
    replies: Receiver<Result<Frame, FrameError>>,
    stderr: Arc<Mutex<Tail>>,
    action_dim: usize,
    needs: ObsNeeds,
    /// Set once the worker failed: every later call reports it again.
    dead: Option<String>,
}

impl fmt::Debug for BridgeEnv {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("BridgeEnv")
            .field("target", &self.target.to_string())
            .field("pid", &self.child.id())
            .field("action_dim", &self.action_dim)
            .finish()
    }
}

impl BridgeEnv {
    /// Starts a worker hosting `target`, which will be observed with `needs`.
    pub fn spawn(
        target: &Target,
        needs: ObsNeeds,
        options: &BridgeOptions,
    ) -> Result<Self, EnvError> {
        let python = options.interpreter(target)?;
        let mut child = Command::new(&python)
            .args(["-u", "-c", WORKER_SOURCE])
            .env("PYTHONUNBUFFERED", "1")
            .env("PYGAME_HIDE_SUPPORT_PROMPT", "1")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| BridgeError::Spawn {
                python: python.display().to_string(),
                error: e.to_string(),
            })?;
        let (Some(stdin), Some(stdout), Some(stderr)) =
            (child.stdin.take(), child.stdout.take(), child.stderr.take())
        else {
            let _ = child.kill();
            return Err(BridgeError::Spawn {
                python: python.display().to_string(),
                error: "no pipes to the worker".into(),
            }
            .into());
        };
        let tail = Arc::new(Mutex::new(Tail::default()));
        spawn_stderr_reader(stderr, Arc::clone(&tail));
        let mut env = Self {
            target: target.clone(),
            options: options.clone(),
            child,
            stdin: Some(stdin),
            replies: spawn_reply_reader(stdout),
            stderr: tail,
            action_dim: 0,
            needs,
            dead: None,
        };
        let hello = json!({
            "op": "hello",
            "target": target.to_string(),
            "needs": {
                "env_state": needs.env_state,
                "image": needs.image.map(|(w, h)| [w, h]),
                "wrist_image": needs.wrist_image,
            },
        });
        let reply = env.request(Frame::new(hello), options.startup_timeout_s)?;
        let protocol = reply.header.get("protocol").and_then(Value::as_u64);
        if protocol != Some(PROTOCOL) {
            return Err(env.protocol(
                "hello",
                format!("protocol {protocol:?}: expected {PROTOCOL}"),
            ));
        }
        env.action_dim = reply
            .header
            .get("action_dim")
            .and_then(Value::as_u64)
            .filter(|&d| d > 0)
            .ok_or_else(|| env.protocol("hello", "no positive \"action_dim\""))?
            as usize;
        Ok(env)
    }

    /// The target this worker hosts.
    pub fn target(&self) -> &Target {
        &self.target
    }

    /// The observations this worker was started for.
    pub fn needs(&self) -> ObsNeeds {
        self.needs
    }

    /// Whether the worker can still serve requests (it has not crashed, hung or spoken out
    /// of protocol). A refused request leaves it alive.
    pub fn is_alive(&self) -> bool {
        self.dead.is_none()
    }

    /// The worker's stderr so far (its last few KB).
    pub fn stderr_tail(&self) -> String {
        self.stderr
            .lock()
            .map(|t| String::from_utf8_lossy(&t.0).into_owned())
            .unwrap_or_default()
    }

    /// The camera frame `name` of an `observe` reply, checked to be `[h, w, 3]` u8, when
    /// `size` (width, height) asks for one.
    fn frame_array(
        &self,
        reply: &Frame,
        name: &str,
        size: Option<(usize, usize)>,
    ) -> Result<Option<Vec<u8>>, EnvError> {
        let Some((w, h)) = size else {
            return Ok(None);
        };
        let a = reply
            .array(name)
            .ok_or_else(|| self.protocol("observe", format!("no {name:?} array")))?;
        match &a.data {
            ArrayData::U8(px) if a.shape == [h, w, 3] => Ok(Some(px.clone())),
            _ => Err(self.protocol(
                "observe",
                format!("{name} of shape {:?}: expected [{h}, {w}, 3] u8", a.shape),
            )),
        }
    }

    fn protocol(&self, op: &str, error: impl Into<String>) -> EnvError {
        BridgeError::Protocol {
            target: self.target.to_string(),
            op: op.into(),
            error: error.into(),
        }
        .into()
    }

    /// Sends `frame` and waits up to `timeout_s` for the answer (an `ok` frame).
    fn request(&mut self, frame: Frame, timeout_s: f64) -> Result<Frame, EnvError> {
        let op = frame
            .header
            .get("op")
            .and_then(Value::as_str)
            .unwrap_or("?")
            .to_string();
        if let Some(why) = &self.dead {
            return Err(self.protocol(&op, format!("the worker failed earlier: {why}")));
        }
        let sent = match self.stdin.as_mut() {
            Some(w) => write_frame(w, &frame),
            None => Err(FrameError::Io(std::io::ErrorKind::BrokenPipe.into())),
        };
        let reply = match sent {
            Ok(()) => self
                .replies
                .recv_timeout(Duration::from_secs_f64(timeout_s)),
            // A closed pipe means the worker is gone: report how it ended.
            Err(_) => Err(RecvTimeoutError::Disconnected),
        };
        let result = match reply {
            Ok(Ok(f)) => Ok(f),
            Ok(Err(e)) => Err(self.protocol(&op, e.to_string())),
            Err(RecvTimeoutError::Timeout) => {
                let _ = self.child.kill();
                let _ = self.child.wait();
                Err(BridgeError::Hung {
                    target: self.target.to_string(),
                    op: op.clone(),
                    seconds: timeout_s,
                    stderr: self.stderr_tail(),
                }
                .into())
            }
            Err(RecvTimeoutError::Disconnected) => Err(self.exited(&op)),
        };
        let reply = match result {
            Ok(f) => f,
            Err(e) => {
                self.dead = Some(e.to_string());
                return Err(e);
            }
        };
        if reply.header.get("ok") == Some(&Value::Bool(true)) {
            return Ok(reply);
        }
        let message = reply
            .header
            .get("error")
            .and_then(Value::as_str)
            .unwrap_or("no message")
            .to_string();
        Err(BridgeError::Refused {
            target: self.target.to_string(),
            op,
            message,
        }
        .into())
    }

    /// The worker's end, once its stdout closed.
    fn exited(&mut self, op: &str) -> EnvError {
        // Its stderr may still be draining: wait for the process, then a moment for the pipe.
        let status = match self.child.wait() {
            Ok(s) => s.to_string(),
            Err(e) => format!("status unknown: {e}"),
        };
        std::thread::sleep(Duration::from_millis(50));
        BridgeError::Exited {
            target: self.target.to_string(),
            op: op.into(),
            status,
            stderr: self.stderr_tail(),
        }
        .into()
    }

    fn score(&self, reply: &Frame, op: &str) -> Result<f64, EnvError> {
        reply
            .header
            .get("score")
            .and_then(Value::as_f64)
            .filter(|s| s.is_finite())
            .ok_or_else(|| self.protocol(op, "no finite \"score\""))
    }
}

impl BridgeEnv {
    /// The target's scripted expert's action for the current state (robomimic tasks: from
    /// the simulator's ground-truth poses; the expert restarts at every reset). Targets
    /// without an expert refuse ([`BridgeError::Refused`]).
    pub fn expert_action(&mut self) -> Result<Vec<f32>, EnvError> {
        let reply = self.request(Frame::new(json!({"op": "expert"})), self.options.timeout_s)?;
        match reply.array("action").map(|a| &a.data) {
            Some(ArrayData::F32(v)) if v.len() == self.action_dim => Ok(v.clone()),
            _ => Err(self.protocol(
                "expert",
                format!("no f32 \"action\" of {} values", self.action_dim),
            )),
        }
    }
}

impl Environment for BridgeEnv {
    fn action_dim(&self) -> usize {
        self.action_dim
    }

    fn reset(&mut self, seed: u64) -> Result<f64, EnvError> {
        let reply = self.request(
            Frame::new(json!({"op": "reset", "seed": seed})),
            self.options.timeout_s,
        )?;
        self.score(&reply, "reset")
    }

    fn observe(&mut self, needs: ObsNeeds) -> Result<Observation, EnvError> {
        if needs != self.needs {
            return Err(self.protocol(
                "observe",
                format!(
                    "observed with {needs:?}; the worker was started for {:?}",
                    self.needs
                ),
            ));
        }
        let reply = self.request(Frame::new(json!({"op": "observe"})), self.options.timeout_s)?;
        let floats = |name: &str| match reply.array(name).map(|a| &a.data) {
            Some(ArrayData::F32(v)) => Ok(Some(v.clone())),
            None => Ok(None),
            Some(_) => Err(self.protocol("observe", format!("array {name:?} is not f32"))),
        };
        let state =
            floats("state")?.ok_or_else(|| self.protocol("observe", "no \"state\" array"))?;
        let env_state = floats("env_state")?;
        if needs.env_state && env_state.is_none() {
            return Err(self.protocol("observe", "no \"env_state\" array"));
        }
        let image = self.frame_array(&reply, "image", needs.image)?;
        // The worker refuses a wrist camera without `image` (and on targets without one).
        let wrist = needs.image.filter(|_| needs.wrist_image);
        let wrist_image = self.frame_array(&reply, "wrist_image", wrist)?;
        Ok(Observation {
            state,
            env_state: env_state.filter(|_| needs.env_state),
            image,
            wrist_image,
        })
    }

    fn step(&mut self, action: &[f32]) -> Result<Outcome, EnvError> {
        if action.len() != self.action_dim {
            return Err(EnvError::ActionShape {
                got: action.len(),
                expected: self.action_dim,
            });
        }
        let frame = Frame::new(json!({"op": "step"})).with_f32("action", action);
        let reply = self.request(frame, self.options.timeout_s)?;
        let success = reply
            .header
            .get("success")
            .and_then(Value::as_bool)
            .ok_or_else(|| self.protocol("step", "no boolean \"success\""))?;
        Ok(Outcome {
            score: self.score(&reply, "step")?,
            success,
        })
    }
}

impl Drop for BridgeEnv {
    fn drop(&mut self) {
        if self.dead.is_none()
            && let Some(w) = self.stdin.as_mut()
        {
            let _ = write_frame(w, &Frame::new(json!({"op": "close"})));
        }
        // Closing stdin ends a worker that missed the close; kill one that still runs.
        self.stdin = None;
        for _ in 0..20 {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Reads the worker's frames on a thread, so that a request can wait with a timeout.
fn spawn_reply_reader(stdout: impl Read + Send + 'static) -> Receiver<Result<Frame, FrameError>> {
    let (tx, rx) = sync_channel(1);
    std::thread::spawn(move || {
        let mut r = BufReader::new(stdout);
        loop {
            match read_frame(&mut r) {
                Ok(Some(f)) => {
                    if tx.send(Ok(f)).is_err() {
                        return;
                    }
                }
                // End of stream: dropping the sender tells the waiting request.
                Ok(None) => return,
                Err(e) => {
                    let _ = tx.send(Err(e));
                    return;
                }
            }
        }
    });
    rx
}

fn spawn_stderr_reader(stderr: impl Read + Send + 'static, tail: Arc<Mutex<Tail>>) {
    std::thread::spawn(move || {
        let mut r = BufReader::new(stderr);
        let mut line = Vec::new();
        while matches!(r.read_until(b'\n', &mut line), Ok(n) if n > 0) {
            if let Ok(mut t) = tail.lock() {
                t.push(&line);
            }
            line.clear();
        }
    });
}

#[cfg(test)]
mod tests;
