//! Typed errors of the simulator.

use crate::rng::RngError;

/// What can go wrong when driving a [`crate::PushT`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// An action with a NaN or infinite coordinate; the state is left unchanged.
    #[error("action {action:?} is not finite: expected an agent target (x, y) in px")]
    NonFiniteAction {
        /// The rejected action.
        action: [f64; 2],
    },
    /// A state with a NaN or infinite entry.
    #[error("state {state:?} is not finite: expected [agent_x, agent_y, block_x, block_y, angle]")]
    NonFiniteState {
        /// The rejected state.
        state: [f64; 5],
    },
    /// The seed cannot be used with the chosen reset stream.
    #[error(transparent)]
    Rng(#[from] RngError),
    /// An environment of a `VecEnv` tick that gave no result (its worker thread was lost).
    #[error("environment {index} gave no result for this tick: its worker thread was lost")]
    NoResult {
        /// The environment's index in the batch.
        index: usize,
    },
    /// A batch of actions whose length does not match the number of environments.
    #[error("got {actions} actions for {envs} environments")]
    BatchSize {
        /// Actions given.
        actions: usize,
        /// Environments in the batch.
        envs: usize,
    },
}
