//! Isowall's transport. It only moves bytes: QUIC connections (quinn) with mutual TLS against the
//! wall's own certificate authority ([`tls`]; the certificates made by [`keygen`]), and
//! length-prefixed [`Message`]s on one bidirectional stream per connection ([`transport`]),
//! encoded by the model's one codec module; in object space, nodes' pixels to each other on a
//! stream per frame ([`pixels`]); and the clock its processes share ([`clock`]). The protocol logic lives in the model's state machines
//! (`isowall_model::barrier`, `isowall_model::node_machine`); the binaries drive them with what
//! arrives here.

pub mod clock;
pub mod keygen;
pub mod pixels;
pub mod tls;
pub mod transport;

pub use keygen::{keygen, CaMode, KeygenReport};
pub use tls::{Identity, TlsError};
pub use transport::{Channel, NetError, ALPN};

use isowall_model::messages::Message;

/// Re-exported for the binaries: what travels.
pub type WireMessage = Message;
