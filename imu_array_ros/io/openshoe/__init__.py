"""OpenShoe serial protocol: streaming packet framing and capture import."""
