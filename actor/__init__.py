"""zenrl.actor"""
