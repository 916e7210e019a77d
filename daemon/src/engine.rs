//! The inference path: shared preprocessing (validation + pen-path resampling, the same code
//! the training data went through) followed by the shipped embedding network.

use std::path::Path;

use guardian_models::embedder::{EMBED_DIM, EmbedError, Embedder, Embedding, LoadModelError};
use guardian_models::features::PenPoint;
use guardian_models::kinematics::Robot;
use guardian_shared::trajectory::{InvalidTrajectory, Resampled, STEPS, Waypoint};

/// Why a trajectory could not be embedded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EmbedFailure {
    /// Validation rejected it.
    #[error(transparent)]
    Invalid(#[from] InvalidTrajectory),
    /// The network failed (never turned into a verdict).
    #[error(transparent)]
    Internal(#[from] EmbedError),
}

/// The loaded model and the robot it serves (the embedder computes pen paths with the
/// robot's forward kinematics; trajectories are validated against its limits).
#[derive(Debug, Clone)]
pub struct Engine {
    embedder: Embedder,
}

/// [`Engine::load`] failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadEngineError {
    /// The weights could not be loaded.
    #[error(transparent)]
    Model(#[from] LoadModelError),
    /// The model cannot serve the robot.
    #[error(transparent)]
    Robot(#[from] EmbedError),
}

impl Engine {
    /// Load and verify weights (shape and checksum are checked by the model crate) for
    /// `robot`.
    pub fn load(path: &Path, robot: Robot) -> Result<Self, LoadEngineError> {
        Ok(Self {
            embedder: Embedder::load(path)?.with_robot(robot)?,
        })
    }

    /// Wrap an already loaded embedder (serving the robot it was given).
    pub fn from_embedder(embedder: Embedder) -> Self {
        Self { embedder }
    }

    /// The robot served.
    pub fn robot(&self) -> &Robot {
        self.embedder.robot()
    }

    /// The embedding network.
    pub fn embedder(&self) -> &Embedder {
        &self.embedder
    }

    /// The model's version string.
    pub fn version(&self) -> &str {
        self.embedder.version()
    }

    /// Embedding length.
    pub fn dim(&self) -> usize {
        EMBED_DIM
    }

    /// Embed already preprocessed trajectories in one forward pass (micro-batching).
    pub fn embed_resampled(&self, xs: &[Resampled]) -> Result<Vec<Embedding>, EmbedError> {
        self.embedder.embed_batch(xs)
    }

    /// Embed one preprocessed trajectory and return the pen path its features came from.
    pub fn embed_with_pen_path(
        &self,
        x: &Resampled,
    ) -> Result<(Embedding, [PenPoint; STEPS]), EmbedError> {
        self.embedder.embed_with_pen_path(x)
    }

    /// Validate against the robot's limits and resample raw waypoints of the served robot.
    pub fn preprocess(&self, waypoints: &[Waypoint]) -> Result<Resampled, InvalidTrajectory> {
        guardian_models::preprocess::preprocess_with(self.robot(), waypoints)
    }

    /// Validate, resample and embed raw waypoints.
    pub fn embed(&self, waypoints: &[Waypoint]) -> Result<Vec<f32>, EmbedFailure> {
        let x = self.preprocess(waypoints)?;
        Ok(self.embedder.embed(&x)?.to_vec())
    }
}
