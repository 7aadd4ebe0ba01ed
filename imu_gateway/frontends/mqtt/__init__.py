"""The MQTT front end: state, availability, commands and Home Assistant discovery on
``{base}/{gateway_id}/…`` (docs/mqtt.md).  ``client.MqttClient`` is the front end;
the transport under it is ``imu_gateway.mqtt_link``."""
