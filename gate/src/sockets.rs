//! Keeping the DDS sockets to the interface of `only-networks` (issue 51, item 4).
//!
//! RustDDS 0.15 uses `only-networks` for the locators it announces and the multicast groups
//! it joins, but binds its UDP sockets (per participant: SPDP multicast and unicast, user
//! traffic multicast and unicast, the sender) to 0.0.0.0 and has no option for the bind
//! address, so a datagram another host sends to the gate's well-known ports still reaches
//! them. Right after a participant is built, the gate binds each of its new sockets that is
//! bound to an unspecified address to the one interface that carries the `only-networks`
//! addresses (`SO_BINDTODEVICE`, allowed unprivileged since Linux 5.7 on a socket not yet
//! bound to a device); the kernel then gives such a socket only datagrams that came in on
//! that interface.
//!
//! The participant's sockets are those the process holds after `build()` and did not hold
//! before: RustDDS makes all of them before `build()` returns (its listeners in `build()`
//! itself, its sender in the event loop, which `build()` waits for). The gate builds its
//! participants one after the other, and nothing else in it makes IP sockets.
//!
//! The same listing checks that a participant got its user-traffic port ([`new_udp_ports`],
//! used by `node::context`): RustDDS 0.15 announces its writers (SEDP) on the user-traffic
//! port of its participant id (`DiscoveredWriterData::new`) even when another process held
//! that port and its listener fell back to an ephemeral one.

use std::collections::{BTreeMap, BTreeSet};
use std::ffi::OsString;
use std::net::{IpAddr, SocketAddr};
use std::os::fd::{BorrowedFd, RawFd};

use nix::sys::socket::{SockType, SockaddrStorage, getsockname, getsockopt, setsockopt, sockopt};

/// Why the DDS sockets cannot be kept to the interface of `only-networks`; the gate does not
/// start then (the operator asked for a restriction it cannot give).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RestrictError {
    /// An `only-networks` address is on no interface of this host.
    #[error("only-networks: {addr} is the address of no interface on this host")]
    NoInterface {
        /// The address.
        addr: IpAddr,
    },
    /// The `only-networks` addresses are on more than one interface.
    #[error(
        "only-networks: the addresses are on {} interfaces ({}); the gate keeps its DDS sockets to one interface, so list the addresses of one",
        interfaces.len(),
        interfaces.join(", ")
    )]
    SeveralInterfaces {
        /// The interfaces, by name.
        interfaces: Vec<String>,
    },
    /// The host's interfaces could not be listed.
    #[error("listing the network interfaces: {0}")]
    Interfaces(#[source] nix::Error),
    /// The process's open files could not be listed.
    #[error("listing the process's sockets in /proc/self/fd: {0}")]
    Proc(#[source] std::io::Error),
    /// The participant's sockets were not found.
    #[error("found no UDP socket of the new DDS participant, so cannot keep it to {device}")]
    NoSockets {
        /// The interface.
        device: String,
    },
    /// `SO_BINDTODEVICE` failed.
    #[error(
        "binding the DDS socket on {local} to interface {device} (SO_BINDTODEVICE): {source}; \
         unprivileged processes may do this from Linux 5.7 on (older kernels: CAP_NET_RAW). \
         Else leave only-networks empty and drop other hosts' datagrams outside the gate \
         (guardian-gate.service: IPAddressDeny=any, IPAddressAllow=localhost)"
    )]
    Bind {
        /// The socket's local address.
        local: SocketAddr,
        /// The interface.
        device: String,
        /// The error.
        #[source]
        source: nix::Error,
    },
}

/// The one interface that carries every address of `only_networks`; `None` if it is empty
/// (no restriction).
pub fn interface_of(only_networks: &[IpAddr]) -> Result<Option<String>, RestrictError> {
    if only_networks.is_empty() {
        return Ok(None);
    }
    let mut names: BTreeMap<IpAddr, BTreeSet<String>> = BTreeMap::new();
    for ifa in nix::ifaddrs::getifaddrs().map_err(RestrictError::Interfaces)? {
        if let Some(ip) = ifa
            .address
            .as_ref()
            .and_then(socket_addr_of)
            .map(|s| s.ip())
        {
            names.entry(ip).or_default().insert(ifa.interface_name);
        }
    }
    let mut all = BTreeSet::new();
    for &addr in only_networks {
        match names.get(&addr) {
            Some(n) => all.extend(n.iter().cloned()),
            None => return Err(RestrictError::NoInterface { addr }),
        }
    }
    let mut all: Vec<String> = all.into_iter().collect();
    match all.len() {
        1 => Ok(all.pop()),
        _ => Err(RestrictError::SeveralInterfaces { interfaces: all }),
    }
}

/// The IPv4 or IPv6 address and port of `a` (`None` for another family).
fn socket_addr_of(a: &SockaddrStorage) -> Option<SocketAddr> {
    if let Some(v4) = a.as_sockaddr_in() {
        Some(SocketAddr::new(v4.ip().into(), v4.port()))
    } else {
        a.as_sockaddr_in6()
            .map(|v6| SocketAddr::new(v6.ip().into(), v6.port()))
    }
}

/// The sockets the process holds: fd number → socket inode (from the `socket:[inode]`
/// links in /proc/self/fd; the inode tells a new socket from an old one whose number was
/// reused).
pub fn sockets() -> Result<BTreeMap<RawFd, u64>, RestrictError> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir("/proc/self/fd").map_err(RestrictError::Proc)? {
        let entry = entry.map_err(RestrictError::Proc)?;
        let Some(fd) = entry.file_name().to_str().and_then(|s| s.parse().ok()) else {
            continue;
        };
        // Gone since the listing (e.g. read_dir's own fd): not a socket of ours.
        let Ok(target) = std::fs::read_link(entry.path()) else {
            continue;
        };
        let inode = target
            .to_str()
            .and_then(|t| t.strip_prefix("socket:["))
            .and_then(|t| t.strip_suffix(']'))
            .and_then(|t| t.parse().ok());
        if let Some(inode) = inode {
            out.insert(fd, inode);
        }
    }
    Ok(out)
}

/// Binds every UDP socket the process holds now and did not hold at `before` (a
/// [`sockets`] snapshot), if bound to an unspecified address (0.0.0.0, ::), to `device`;
/// returns how many it bound. Errors if it finds no new UDP socket at all. The caller holds
/// the participant that made them (see [`borrow`]).
pub fn bind_new(before: &BTreeMap<RawFd, u64>, device: &str) -> Result<usize, RestrictError> {
    let name = OsString::from(device);
    let udp = new_udp(before)?;
    if udp.is_empty() {
        return Err(RestrictError::NoSockets {
            device: device.to_owned(),
        });
    }
    let mut bound = 0;
    for (fd, local) in udp {
        if local.ip().is_unspecified() {
            bind_to_device(fd, &name).map_err(|source| RestrictError::Bind {
                local,
                device: device.to_owned(),
                source,
            })?;
            bound += 1;
        } else {
            tracing::debug!("DDS socket on {local} left as it is (bound to an address)");
        }
    }
    Ok(bound)
}

/// The local ports of the UDP sockets the process holds now and did not hold at `before`.
/// The caller holds the participant that made them (see [`borrow`]).
pub fn new_udp_ports(before: &BTreeMap<RawFd, u64>) -> Result<BTreeSet<u16>, RestrictError> {
    Ok(new_udp(before)?
        .into_iter()
        .map(|(_, l)| l.port())
        .collect())
}

/// The UDP sockets (fd, local address) the process holds now and did not hold at `before`.
fn new_udp(before: &BTreeMap<RawFd, u64>) -> Result<Vec<(RawFd, SocketAddr)>, RestrictError> {
    let old: BTreeSet<u64> = before.values().copied().collect();
    Ok(sockets()?
        .into_iter()
        .filter(|(_, inode)| !old.contains(inode))
        .filter_map(|(fd, _)| udp_local(fd).map(|local| (fd, local)))
        .collect())
}

/// A participant's discovery (SPDP/SEDP) unicast port ([`unicast_port`], d1 = 10).
pub fn discovery_unicast_port(domain: u16, participant_id: u16) -> u32 {
    unicast_port(domain, participant_id, 10)
}

/// A participant's user-traffic unicast port ([`unicast_port`], d3 = 11).
pub fn user_unicast_port(domain: u16, participant_id: u16) -> u32 {
    unicast_port(domain, participant_id, 11)
}

/// RTPS's well-known unicast port with offset `d` (RTPS 2.5, 9.6.2.3, with the defaults
/// PB 7400, DG 250, PG 2, as RustDDS uses them).
fn unicast_port(domain: u16, participant_id: u16, d: u32) -> u32 {
    7400 + 250 * u32::from(domain) + d + 2 * u32::from(participant_id)
}

/// `fd`'s local address, if it is an IPv4 or IPv6 UDP socket.
fn udp_local(fd: RawFd) -> Option<SocketAddr> {
    let local = socket_addr_of(&getsockname::<SockaddrStorage>(fd).ok()?)?;
    let kind = getsockopt(&borrow(fd), sockopt::SockType).ok()?;
    (kind == SockType::Datagram).then_some(local)
}

fn bind_to_device(fd: RawFd, device: &OsString) -> nix::Result<()> {
    setsockopt(&borrow(fd), sockopt::BindToDevice, device)
}

/// The socket `fd` of the participant just built, borrowed for a socket option.
#[allow(unsafe_code)]
fn borrow<'a>(fd: RawFd) -> BorrowedFd<'a> {
    // SAFETY: only called (through `new_udp`, for `bind_new` and `new_udp_ports`) on fds
    // found in /proc/self/fd a moment ago as sockets that did not exist before the
    // participant was built, i.e. the participant's. The callers hold the participant, and
    // RustDDS closes its sockets only when it is dropped, so the fd stays open while
    // borrowed. The borrow is used for getsockopt and setsockopt only and never outlives
    // the call; nothing takes ownership or closes it.
    // (std has no safe way to reach a socket a library holds by its number, and
    // `pidfd_getfd`, which could dup it safely, is in the unit's denied `@debug` syscalls
    // and in Docker's default seccomp profile.)
    unsafe { BorrowedFd::borrow_raw(fd) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_is_on_lo_and_empty_is_no_restriction() {
        assert_eq!(interface_of(&[]).unwrap(), None);
        assert_eq!(
            interface_of(&["127.0.0.1".parse().unwrap()])
                .unwrap()
                .as_deref(),
            Some("lo")
        );
    }

    #[test]
    fn an_address_on_no_interface_is_an_error() {
        // TEST-NET-3 (RFC 5737): documentation only, on no interface here.
        let err = interface_of(&["203.0.113.77".parse().unwrap()]).unwrap_err();
        assert!(matches!(err, RestrictError::NoInterface { .. }), "{err}");
    }

    #[test]
    fn new_wildcard_udp_sockets_are_bound_and_old_ones_are_not() {
        let old = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
        let before = sockets().unwrap();
        let wildcard = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
        let specific = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let tcp = std::net::TcpListener::bind("0.0.0.0:0").unwrap();
        // Other tests of this process may make sockets meanwhile: at least ours is bound.
        assert!(bind_new(&before, "lo").unwrap() >= 1);
        let dev =
            |s: &dyn std::os::fd::AsFd| getsockopt(&s.as_fd(), sockopt::BindToDevice).unwrap();
        assert_eq!(dev(&wildcard), "lo");
        assert_eq!(dev(&specific), "");
        assert_eq!(dev(&tcp), "");
        assert_eq!(dev(&old), "");
    }
}
