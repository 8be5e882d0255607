//! The certificates of X.509 user identity tokens, for the authenticator.
//!
//! async-opcua checks a token's signature (the client holds the key) and
//! then hands the authenticator only the certificate's SHA-1 thumbprint.
//! To check the certificate's trust and read its role extension the face
//! needs the certificate itself: [`Stash`] is a type loader put before the
//! generated ones ([`install`]) that sees each `X509IdentityToken` as it is
//! decoded, keeps its certificate by thumbprint (the last [`Stash::KEEP`])
//! and hands the token on unchanged.

use std::collections::VecDeque;
use std::io::Read;
use std::sync::{Arc, Mutex};

use opcua::crypto::{Thumbprint, X509};
use opcua::server::ServerHandle;
use opcua::types::{
    BinaryDecodable, Context, DynEncodable, EncodingResult, NodeId, ObjectId, TypeLoader,
    TypeLoaderCollection, TypeLoaderPriority, X509IdentityToken,
};

/// The certificates of the X.509 user tokens decoded lately.
#[derive(Default)]
pub struct Stash {
    certs: Mutex<VecDeque<(String, Vec<u8>)>>,
}

impl Stash {
    /// Certificates kept: more than sessions can activate at once.
    const KEEP: usize = 64;

    fn put(&self, der: Vec<u8>) {
        let Ok(cert) = X509::from_der(&der) else {
            return;
        };
        let thumb = cert.thumbprint().as_hex_string();
        let mut certs = self.certs.lock().unwrap_or_else(|p| p.into_inner());
        certs.retain(|(t, _)| *t != thumb);
        certs.push_back((thumb, der));
        while certs.len() > Self::KEEP {
            certs.pop_front();
        }
    }

    /// The certificate (DER) with `thumbprint`, taken out.
    pub fn take(&self, thumbprint: &Thumbprint) -> Option<Vec<u8>> {
        let hex = thumbprint.as_hex_string();
        let mut certs = self.certs.lock().unwrap_or_else(|p| p.into_inner());
        let i = certs.iter().position(|(t, _)| *t == hex)?;
        certs.remove(i).map(|(_, der)| der)
    }
}

/// The type loader that fills a [`Stash`].
struct Loader(Arc<Stash>);

impl TypeLoader for Loader {
    fn load_from_binary(
        &self,
        node_id: &NodeId,
        stream: &mut dyn Read,
        ctx: &Context<'_>,
        _length: Option<usize>,
    ) -> Option<EncodingResult<Box<dyn DynEncodable>>> {
        if *node_id != ObjectId::X509IdentityToken_Encoding_DefaultBinary {
            return None;
        }
        Some(X509IdentityToken::decode(stream, ctx).map(|token| {
            if let Some(der) = token.certificate_data.value.as_ref() {
                self.0.put(der.clone());
            }
            Box::new(token) as Box<dyn DynEncodable>
        }))
    }

    fn priority(&self) -> TypeLoaderPriority {
        TypeLoaderPriority::Core
    }
}

/// Puts `stash`'s loader before the server's own (before the first
/// connection): `ServerBuilder::with_type_loader` would put it after the
/// generated one, which has the same priority.
pub fn install(handle: &ServerHandle, stash: Arc<Stash>) {
    let mut loaders = handle.info().type_loaders.write();
    let mut ours = TypeLoaderCollection::new_empty();
    ours.add(Arc::new(Loader(stash)));
    for loader in loaders.iter() {
        ours.add(loader.clone());
    }
    *loaders = ours;
}
