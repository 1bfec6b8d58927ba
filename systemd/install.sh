#!/usr/bin/env bash
# Install Wingman as a systemd service on a JetPack 6 board (Ubuntu 22.04, aarch64), from this checkout.
#
#   sudo systemd/install.sh [--serial /dev/ttyTHS1] [--vehicle-id follower1] [--gpu] [--broker] [--start]
#                           [--prefix /opt/wingman]
#
# Creates the system user `wingman`, copies the code to PREFIX, builds PREFIX/.venv (with the system's
# site-packages, so NVIDIA's JetPack torch / onnxruntime-gpu / TensorRT wheels installed beforehand are
# used), generates the secrets in /etc/wingman/credentials (MAVLink signing key, an operator's command key,
# a formation key, the broker password; root, mode 0600, handed to the service as systemd credentials),
# installs /etc/wingman/wingman.toml if absent (MAVLink signing on), the unit, a `companion` wrapper in
# /usr/local/bin, with --gpu a drop-in that lets the service open the Jetson GPU nodes, and with --broker
# a local mosquitto with TLS, password authentication, per-vehicle ACLs and a 64 KiB packet limit.
# Idempotent: existing secrets, certificates and config are kept.
set -euo pipefail

PREFIX=/opt/wingman
SERIAL=/dev/ttyTHS1
VEHICLE_ID=follower1
GPU=0
BROKER=0
START=0
while [ $# -gt 0 ]; do
    case "$1" in
        --prefix) PREFIX=$2; shift 2 ;;
        --serial) SERIAL=$2; shift 2 ;;
        --vehicle-id) VEHICLE_ID=$2; shift 2 ;;
        --gpu) GPU=1; shift ;;
        --broker) BROKER=1; shift ;;
        --start) START=1; shift ;;
        -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
        *) echo "install.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
[ "$(id -u)" -eq 0 ] || { echo "install.sh: run as root (sudo)" >&2; exit 1; }
case "$SERIAL" in /dev/*) ;; *) echo "install.sh: --serial must be a /dev path" >&2; exit 2 ;; esac
case "$VEHICLE_ID" in *[!A-Za-z0-9_-]*|"") echo "install.sh: --vehicle-id: letters, digits, _ and -" >&2; exit 2 ;; esac
SRC=$(cd "$(dirname "$0")/.." && pwd)
UNIT_DIR=/etc/systemd/system
CRED_SRC=/etc/wingman/credentials
# Where systemd puts them for the running service (LoadCredential= in the unit).
CRED_RUN=/run/credentials/wingman.service

echo "== user and groups"
getent group wingman >/dev/null || groupadd --system wingman
id -u wingman >/dev/null 2>&1 || useradd --system --gid wingman --home-dir /var/lib/wingman \
    --no-create-home --shell /usr/sbin/nologin --comment "Wingman companion service" wingman

echo "== packages (python venv, libusb for the RealSense)"
need=()
for p in python3-venv libusb-1.0-0; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}"
fi

echo "== code to $PREFIX"
mkdir -p "$PREFIX"
if git -C "$SRC" rev-parse --git-dir >/dev/null 2>&1; then
    git -C "$SRC" archive --format=tar HEAD | tar -x -C "$PREFIX"
else
    tar -C "$SRC" --exclude=.venv --exclude=runs --exclude=data -cf - . | tar -x -C "$PREFIX"
fi
chown -R root:root "$PREFIX"
chmod -R go-w "$PREFIX"

echo "== venv (system site-packages visible for JetPack's torch/TensorRT)"
[ -x "$PREFIX/.venv/bin/python" ] || python3 -m venv --system-site-packages "$PREFIX/.venv"
"$PREFIX/.venv/bin/python" -m pip install -q --disable-pip-version-check "$PREFIX[realsense]"

echo "== secrets (root only; the service gets them as systemd credentials)"
install -d -m 0750 -o root -g wingman /etc/wingman
install -d -m 0700 -o root -g root "$CRED_SRC"
new_secret() {  # FILE CONTENT-COMMAND: write it once, mode 0600
    [ -s "$CRED_SRC/$1" ] && return 0
    (umask 077; eval "$2" > "$CRED_SRC/$1")
    echo "   generated $CRED_SRC/$1"
}
new_secret mavlink-signing.key 'head -c 32 /dev/urandom | od -An -tx1 | tr -d " \n"; echo'
new_secret command-keys 'printf "operator1 %s\n" "$(head -c 32 /dev/urandom | od -An -tx1 | tr -d " \n")"'
# This vehicle's own share key, bound to the one topic it publishes (its pose): the first line signs. A
# formation adds the other vehicles' lines (and the leader's publisher's) to every vehicle's file.
new_secret formation-keys 'printf "%s %s wingman/%s/pose\n" "$VEHICLE_ID" "$(head -c 32 /dev/urandom | od -An -tx1 | tr -d " \n")" "$VEHICLE_ID"'
new_secret mqtt-password 'head -c 24 /dev/urandom | od -An -tx1 | tr -d " \n"; echo'

echo "== config"
if [ ! -f /etc/wingman/wingman.toml ]; then
    # MAVLink signing on the serial link, the key given to the autopilot while it is disarmed (over the
    # cable: nothing else listens there); MQTT settings for the broker --broker installs.
    sed -e "s#^vehicle_id = .*#vehicle_id = \"$VEHICLE_ID\"#" \
        -e "s#^url = \"udpin://0.0.0.0:14541\".*#url = \"serial://$SERIAL:921600\"#" \
        -e 's#^signing = false.*#signing = true#' \
        -e "s#^signing_key_file = \"\".*#signing_key_file = \"$CRED_RUN/mavlink-signing.key\"#" \
        -e 's#^signing_provision = false.*#signing_provision = true#' \
        -e 's#^source = "sim".*#source = "realsense"#' \
        -e 's#^model_path = "models/#model_path = "'"$PREFIX"'/models/#' \
        -e 's#^format = "human".*#format = "json"#' \
        -e "/^\[mqtt\]/,/^\[/ s#^port = 1883.*#port = 8883#" \
        -e "/^\[mqtt\]/,/^\[/ s#^username = \"\".*#username = \"$VEHICLE_ID\"#" \
        -e "s#^password_file = \"\".*#password_file = \"$CRED_RUN/mqtt-password\"#" \
        -e 's#^tls = false.*#tls = true#' \
        -e 's#^ca_file = "".*#ca_file = "/etc/wingman/mqtt-ca.crt"#' \
        -e "s#^command_keys_file = \"\".*#command_keys_file = \"$CRED_RUN/command-keys\"#" \
        -e "s#^formation_keys_file = \"\".*#formation_keys_file = \"$CRED_RUN/formation-keys\"#" \
        "$PREFIX/config/wingman.toml" > /etc/wingman/wingman.toml
    chown root:wingman /etc/wingman/wingman.toml
    chmod 0640 /etc/wingman/wingman.toml
    echo "   wrote /etc/wingman/wingman.toml (check [mqtt] host; enable [mqtt] and command_topic, then restart)"
fi

if [ "$BROKER" -eq 1 ]; then
    echo "== broker (mosquitto: TLS on 8883, passwords, ACLs, 64 KiB packets)"
    dpkg-query -W -f='${Status}' mosquitto 2>/dev/null | grep -q "install ok installed" \
        || DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends mosquitto openssl
    certs=/etc/mosquitto/certs/wingman
    install -d -m 0750 -o root -g mosquitto "$certs"
    if [ ! -f "$certs/server.crt" ]; then
        # A CA of this drone's own, and a server certificate for its name and 127.0.0.1.
        (umask 077
         openssl req -x509 -newkey rsa:3072 -nodes -days 3650 -subj "/CN=wingman CA $(hostname)" \
             -keyout "$certs/ca.key" -out "$certs/ca.crt" 2>/dev/null
         openssl req -newkey rsa:3072 -nodes -subj "/CN=$(hostname)" \
             -keyout "$certs/server.key" -out "$certs/server.csr" 2>/dev/null
         printf "subjectAltName=DNS:%s,DNS:localhost,IP:127.0.0.1\n" "$(hostname)" > "$certs/san.ext"
         openssl x509 -req -in "$certs/server.csr" -CA "$certs/ca.crt" -CAkey "$certs/ca.key" \
             -CAcreateserial -days 3650 -extfile "$certs/san.ext" -out "$certs/server.crt" 2>/dev/null)
        chgrp mosquitto "$certs/server.key" && chmod 0640 "$certs/server.key"
        chmod 0644 "$certs/ca.crt" "$certs/server.crt"
        echo "   generated a CA and server certificate in $certs (give ca.crt to the ground station)"
    fi
    install -m 0644 "$certs/ca.crt" /etc/wingman/mqtt-ca.crt
    install -m 0644 "$PREFIX/systemd/mosquitto-wingman.conf" /etc/mosquitto/conf.d/wingman.conf
    install -m 0640 -g mosquitto "$PREFIX/systemd/mosquitto-wingman.acl" /etc/mosquitto/wingman.acl
    [ -f /etc/mosquitto/wingman.passwd ] || (umask 027; : > /etc/mosquitto/wingman.passwd)
    chgrp mosquitto /etc/mosquitto/wingman.passwd
    # On standard input (asked twice), never as an argument: any local user can read a process's arguments.
    pw=$(cat "$CRED_SRC/mqtt-password")
    printf '%s\n%s\n' "$pw" "$pw" | mosquitto_passwd /etc/mosquitto/wingman.passwd "$VEHICLE_ID" >/dev/null
    unset pw
    systemctl restart mosquitto
    echo "   broker user $VEHICLE_ID; add operators: mosquitto_passwd /etc/mosquitto/wingman.passwd NAME"
fi
"$PREFIX/.venv/bin/companion" check-config /etc/wingman/wingman.toml >/dev/null

echo "== unit"
sed -e "s#/opt/wingman#$PREFIX#g" -e "s#^DeviceAllow=/dev/ttyTHS1 rw#DeviceAllow=$SERIAL rw#" \
    "$PREFIX/systemd/wingman.service" > "$UNIT_DIR/wingman.service"
chmod 0644 "$UNIT_DIR/wingman.service"
dropin=$UNIT_DIR/wingman.service.d
if [ "$GPU" -eq 1 ]; then
    # The detector on the GPU needs the Jetson's nvgpu/nvmap/host1x nodes: allow exactly those present.
    mkdir -p "$dropin"
    {
        echo "# Generated by install.sh --gpu on $(hostname): the Jetson GPU nodes for CUDA/TensorRT inference."
        echo "[Service]"
        for node in /dev/nvmap /dev/nvhost-* /dev/nvgpu/igpu0/* /dev/host1x-fence /dev/nvidia*; do
            if [ -c "$node" ]; then echo "DeviceAllow=$node rw"; fi
        done
    } > "$dropin/10-jetson-gpu.conf"
    echo "   GPU drop-in: $(grep -c DeviceAllow "$dropin/10-jetson-gpu.conf") device node(s)"
else
    rm -f "$dropin/10-jetson-gpu.conf"
fi

echo "== operator command"
cat > /usr/local/bin/companion <<WRAP
#!/bin/sh
# Wingman CLI with the installed config (companion status | health | check-config ...).
WINGMAN_CONFIG=\${WINGMAN_CONFIG:-/etc/wingman/wingman.toml} exec $PREFIX/.venv/bin/companion "\$@"
WRAP
chmod 0755 /usr/local/bin/companion

systemctl daemon-reload
if ! out=$(systemd-analyze verify "$UNIT_DIR/wingman.service" 2>&1) || [ -n "$out" ]; then
    echo "install.sh: systemd-analyze verify complained:" >&2; echo "$out" >&2; exit 1
fi
systemctl enable wingman.service >/dev/null
if [ "$START" -eq 1 ]; then systemctl restart wingman.service; fi
echo "installed. Operators: usermod -aG wingman <user>; then: companion status | companion health"
echo "command key for the ground station (operator1): $CRED_SRC/command-keys; formations: append every"
echo "other vehicle's line of its formation-keys (and the leader's publisher's) to $CRED_SRC/formation-keys"
echo "logs: journalctl -u wingman -f      exposure: systemd-analyze security wingman.service"
