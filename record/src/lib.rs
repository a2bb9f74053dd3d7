//! Recording, replay and live view: MCAP files and a Foxglove WebSocket server with Foxglove's schemas (issue 12).
