#!/usr/bin/env bash
# Debian packages the cloud platform and its tests use: Mosquitto (MQTT broker), PostgreSQL 15 with PostGIS, RabbitMQ
# (the cluster mode's broker, roadgrip/cloud/transport/amqp.py), and
# Chromium (headless dashboard tests). Skips what is already installed; needs root (or sudo) otherwise.
set -euo pipefail
packages=(mosquitto mosquitto-clients postgresql-15 postgresql-15-postgis-3 rabbitmq-server chromium)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then
  sudo_cmd=(sudo)
fi
echo "installing Debian packages: ${missing[*]}"
"${sudo_cmd[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
