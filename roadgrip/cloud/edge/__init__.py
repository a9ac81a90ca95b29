"""Vehicles in: the MQTT brokers (Mosquitto, RabbitMQ), the payload format, credentials, rate limit, admission."""
