//! The HTTP service. UNDER CONSTRUCTION by the service helper.
