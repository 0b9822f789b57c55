//! ROS 2 camera messages: their CDR bytes read ([`cdr`], [`messages`]) and turned into the wire
//! types a vsgraphs robot sends ([`convert`]), so that a ROS 2 robot's topics ([`topics`]: where
//! they are on zenoh) and recorded bags enter the same pipeline as an SDK robot's frames.

pub mod cdr;
pub mod convert;
pub mod messages;
pub mod rvl;
pub mod topics;

pub use cdr::{CdrError, Layout};
pub use convert::RosError;
pub use messages::{CameraInfo, CompressedImage, Header, Image, RegionOfInterest};
pub use topics::{KeyFormat, MessageType, TopicError};
