//! The simulated lift: [`model`] is the lift (sans-IO).

pub mod model;
