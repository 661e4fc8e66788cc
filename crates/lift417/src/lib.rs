//! The CiA 417 lift application profile as canlift serves it through the NXg connector: the
//! lift-number rule of CiA 417-4 §4.1.1 ([`lift`]), the object catalog with names, hints,
//! units and limits in the NXg vocabulary of `nxg::meta` ([`catalog`]), what its EMCY codes
//! mean ([`emcy`]) and, with the `sim` feature, the simulated lift (`sim`).

#![warn(missing_docs)]

pub mod catalog;
pub mod emcy;
pub mod lift;
#[cfg(feature = "sim")]
pub mod sim;
