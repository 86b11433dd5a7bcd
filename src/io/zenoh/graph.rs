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

/// A publisher's or subscription's QoS, as its graph token states it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Qos {
    /// Reliable (rmw 1), else best effort (2).
    pub reliable: bool,
    /// Transient local (rmw 1: late joiners get the last `depth` messages), else volatile (2).
    pub transient_local: bool,
    /// Keep last `depth` (history 1).
    pub depth: usize,
}

impl Qos {
    /// rmw's default profile: reliable, volatile, keep last 10.
    pub const DEFAULT: Qos = Qos {
        reliable: true,
        transient_local: false,
        depth: 10,
    };

    /// rmw's sensor-data profile: best effort, volatile, keep last `depth`.
    pub fn sensor_data(depth: usize) -> Qos {
        Qos {
            reliable: false,
            transient_local: false,
            depth,
        }
    }

    /// tf2's static listener: reliable, transient local, keep last 100.
    pub const STATIC_TF: Qos = Qos {
        reliable: true,
        transient_local: true,
        depth: 100,
    };

    /// The token's QoS chunk, every field written: deadline and lifespan unspecified (0, 0),
    /// automatic liveliness (1) with an unspecified lease.
    pub fn key(&self) -> String {
        format!(
            "{}:{}:1,{}:0,0:0,0:1,0,0",
            if self.reliable { 1 } else { 2 },
            if self.transient_local { 1 } else { 2 },
            self.depth
        )
    }
}

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
        qos: &Qos,
    ) -> String {
        let kind = match entity {
            Entity::Publisher => "MP",
            Entity::Subscription => "MS",
        };
        format!(
            "{}/{id}/{kind}/{}/{}/{}/{}/{}",
            self.prefix,
            self.names,
            mangle(&format!("/{}", topic.trim_matches('/'))),
            desc.dds_name(),
            desc.rihs01(),
            qos.key()
        )
    }

    /// Declares a publisher or subscription of `topic`; it leaves the graph when the token
    /// is dropped. Returns the token and its key.
    pub fn declare(
        &self,
        entity: Entity,
        topic: &str,
        desc: &MsgDesc,
        qos: &Qos,
    ) -> Result<(LivelinessToken, String), ZenohError> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let key = self.entity_key(id, entity, topic, desc, qos);
        let token = self
            .session
            .liveliness()
            .declare_token(&key)
            .wait()
            .map_err(zerr)?;
        Ok((token, key))
    }
}
