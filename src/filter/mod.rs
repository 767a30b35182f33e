//! Filters: a generic unscented Kalman filter ([`ukf`]), the bearing-only landmark model
//! the area pipeline runs in it ([`bearing`]), and the 2D particle filter of the indoor
//! pipeline ([`particle`]).
//!
//! Models are traits ([`ProcessModel`], [`MeasurementModel`]) and dimensions are const
//! generics, so a state/measurement size mismatch is a compile error, not a runtime one.

pub mod bearing;
pub mod particle;
pub mod ukf;

pub use bearing::{bearing_noise, BearingModel, StaticLandmark};
pub use ukf::{
    MeasurementModel, PredictedMeasurement, ProcessModel, Ukf, UkfParams, UpdateReport, MAX_STATE,
};

/// Why a filter step was refused. The filter's state is unchanged when one is returned.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum FilterError {
    #[error("non-finite {0}")]
    NonFinite(&'static str),
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    #[error("bad filter parameters: {0}")]
    BadParameters(String),
}
