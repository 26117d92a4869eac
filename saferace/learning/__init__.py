"""The learned driver: networks, collection rounds, training, the learned agent and state
source, and GradCAM. The only package that imports torch; nothing below it imports it."""
