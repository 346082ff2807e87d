#!/usr/bin/env bash
# Make a test/fleet PKI for zenoh mutual TLS with the openssl CLI (EC P-256, valid DAYS days):
#   ca.pem / ca-key.pem          the certificate authority (keep ca-key.pem off the vehicle)
#   router.pem / router-key.pem  the zenoh router: CN and SAN localhost, SAN IP 127.0.0.1 (add yours with ROUTER_SAN)
#   NAME.pem / NAME-key.pem      one client certificate per NAME, CN=NAME: the ACL's cert_common_names
# Usage: deploy/zenoh-certs.sh OUTDIR [NAME ...]   (default names: companion sensor operator)
# Example: ROUTER_SAN="DNS:localhost,IP:127.0.0.1,IP:192.168.1.10" DAYS=365 deploy/zenoh-certs.sh /etc/apf-companion/zenoh
set -euo pipefail
out=${1:?usage: zenoh-certs.sh OUTDIR [NAME ...]}
shift
names=("$@")
[[ ${#names[@]} -gt 0 ]] || names=(companion sensor operator)
days=${DAYS:-30}
router_san=${ROUTER_SAN:-DNS:localhost,IP:127.0.0.1}
mkdir -p "$out"
cd "$out"
umask 077  # private keys readable by the owner only

openssl ecparam -name prime256v1 -genkey -noout -out ca-key.pem
openssl req -x509 -new -key ca-key.pem -sha256 -days "$days" -subj "/CN=apf-companion zenoh CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" -out ca.pem

# leaf NAME CN EXTENDED_KEY_USAGE SUBJECT_ALT_NAME
leaf() {
  openssl ecparam -name prime256v1 -genkey -noout -out "$1-key.pem"
  openssl req -new -key "$1-key.pem" -subj "/CN=$2" -out "$1.csr"
  printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=%s\nsubjectAltName=%s\n' \
    "$3" "$4" >"$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days "$days" -sha256 \
    -extfile "$1.ext" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}
leaf router localhost serverAuth "$router_san"
for name in "${names[@]}"; do
  [[ $name =~ ^[A-Za-z0-9._-]+$ ]] || { echo "zenoh-certs.sh: bad client name '$name'" >&2; exit 2; }
  leaf "$name" "$name" clientAuth "DNS:$name"
done
chmod 644 ./*.pem
chmod 600 ./*-key.pem
echo "zenoh-certs.sh: CA, router and ${names[*]} certificates in $out"
