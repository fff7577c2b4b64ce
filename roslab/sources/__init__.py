"""Source workspaces: .repos files checked, repositories fetched once by the controller, the underlay built."""
