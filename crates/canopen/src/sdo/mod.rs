//! Service data objects (CiA 301 §7.2.4).

pub mod abort;
