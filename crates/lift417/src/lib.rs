//! The CiA 417 lift application profile as canlift serves it through the NXg connector.
//!
//! So far: the metadata vocabulary of NXg SW003 §8 ([`meta`]) and the lift-number rule of
//! CiA 417-4 §4.1.1 ([`lift`]). The object catalog and the simulated lift build on these.

#![warn(missing_docs)]

pub mod lift;
pub mod meta;
