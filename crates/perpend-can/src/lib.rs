//! placeholder until the CANopen issue
