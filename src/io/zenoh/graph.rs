//! hapcloud in the ROS 2 graph of an rmw_zenoh system: the liveliness tokens rmw_zenoh
//! declares for a node and for each of its publishers and subscriptions, so `ros2 node list`
//! and `ros2 topic list` there show hapcloud's node and topics.
//!
//! A token's key is (rmw_zenoh's docs/design.md, "Graph Cache", and liveliness_utils.cpp)
//! `@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/
//! <node name>`, followed for a publisher or subscription by `/<topic>/<DDS type name>/<type
//! hash>/<QoS>`; a `/` inside a name is written `%` (the root namespace is `%`). The QoS chunk
//! lists reliability, durability, history and depth, deadline, lifespan and liveliness, each
//! empty where it is rmw's default profile.

use super::{KeyStyle, ZenohConfig, ZenohError, zerr};
use crate::io::ros2::typedesc::MsgDesc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};
use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;

/// The liveliness key space of rmw_zenoh.
pub const ADMIN_SPACE: &str = "@ros2_lv";

/// rmw's default QoS profile (reliable, volatile, keep last 10): every field left empty.
pub const QOS_DEFAULT: &str = "::,:,:,:,,";

/// What a token stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Entity {
    Publisher,
    Subscription,
}

/// One ROS 2 node per Zenoh session: its token, and the ids of its entities.
pub struct GraphNode {
    session: zenoh::Session,
    /// `@ros2_lv/<domain>/<session id>/<node id>`.
    prefix: String,
    /// `<enclave>/<namespace>/<node name>`, mangled.
    names: String,
    next_id: AtomicU64,
    _token: LivelinessToken,
}

/// The nodes of the open sessions (a session's source and publisher are one node).
static NODES: Mutex<Vec<(zenoh::session::ZenohId, Weak<GraphNode>)>> = Mutex::new(Vec::new());

/// `/` written as `%`, as rmw_zenoh mangles names in a key.
fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

impl GraphNode {
    /// The node of `session` (declared on first use, undeclared when its last user goes);
    /// `None` with zenoh-plugin-ros2dds keys, which have no graph tokens.
    pub fn of(
        session: &zenoh::Session,
        config: &ZenohConfig,
    ) -> Result<Option<Arc<Self>>, ZenohError> {
        if config.keys != KeyStyle::RmwZenoh {
            return Ok(None);
        }
        let zid = session.zid();
        let mut nodes = NODES.lock().unwrap_or_else(PoisonError::into_inner);
        nodes.retain(|(_, n)| n.strong_count() > 0);
        if let Some(node) = nodes
            .iter()
            .find(|(id, _)| *id == zid)
            .and_then(|(_, n)| n.upgrade())
        {
            return Ok(Some(node));
        }
        let prefix = format!("{ADMIN_SPACE}/{}/{zid}/0", config.domain_id);
        let names = format!(
            "%/{}/{}",
            mangle(&config.namespace),
            mangle(&config.node_name)
        );
        let token = session
            .liveliness()
            .declare_token(format!("{prefix}/0/NN/{names}"))
            .wait()
            .map_err(zerr)?;
        let node = Arc::new(Self {
            session: session.clone(),
            prefix,
            names,
            next_id: AtomicU64::new(1),
            _token: token,
        });
        nodes.push((zid, Arc::downgrade(&node)));
        Ok(Some(node))
    }

    /// The key of a publisher or subscription of `topic` carrying `desc`, entity `id`.
    pub fn entity_key(
        &self,
        id: u64,
        entity: Entity,
        topic: &str,
        desc: &MsgDesc,
        qos: &str,
    ) -> String {
        let kind = match entity {
            Entity::Publisher => "MP",
            Entity::Subscription => "MS",
        };
        format!(
            "{}/{id}/{kind}/{}/{}/{}/{}/{qos}",
            self.prefix,
            self.names,
            mangle(&format!("/{}", topic.trim_matches('/'))),
            desc.dds_name(),
            desc.rihs01()
        )
    }

    /// Declares a publisher or subscription of `topic`; it leaves the graph when the token
    /// is dropped.
    pub fn declare(
        &self,
        entity: Entity,
        topic: &str,
        desc: &MsgDesc,
        qos: &str,
    ) -> Result<LivelinessToken, ZenohError> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        self.session
            .liveliness()
            .declare_token(self.entity_key(id, entity, topic, desc, qos))
            .wait()
            .map_err(zerr)
    }
}

/// A best-effort, keep-last-`depth` subscription's QoS (rmw's sensor-data profile).
pub fn sensor_qos(depth: usize) -> String {
    format!("2::,{depth}:,:,:,,")
}
