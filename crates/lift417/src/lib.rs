//! The CiA 417 lift application profile as canlift serves it through the NXg connector: the
//! metadata vocabulary of NXg SW003 §8 ([`meta`]), the lift-number rule of CiA 417-4 §4.1.1
//! ([`lift`]), the object catalog with names, hints, units and limits ([`catalog`]) and the
//! simulated lift ([`sim`]).

#![warn(missing_docs)]

pub mod catalog;
pub mod lift;
pub mod meta;
pub mod sim;
